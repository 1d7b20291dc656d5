"""Command line of the sim worker: ``python -m sim_worker collect ...`` and ``python -m sim_worker serve ...``."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from firp.cli import int_in_range, non_negative_float, open_unit_fraction
from firp.contract import DEFAULT_T, T_MAX, T_MIN


def build_parser() -> argparse.ArgumentParser:
    from sim_worker.tasks import TASK_NAMES

    parser = argparse.ArgumentParser(prog="python -m sim_worker", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect", help="simulate labelled episodes into a robomimic-style HDF5 file (resumable)")
    c.add_argument("--task", required=True, choices=TASK_NAMES)
    c.add_argument("--episodes", required=True, type=int_in_range("--episodes", 1, 1_000_000))
    c.add_argument("--out", required=True, type=Path, help="HDF5 file to write (parts kept beside it until done)")
    c.add_argument("--workers", type=int_in_range("--workers", 1, 256), default=max(1, os.cpu_count() or 1))
    c.add_argument("--seed-offset", type=int_in_range("--seed-offset", 0, 2**31 - 1), default=0,
                   help="episode i uses scene seed seed_offset + i")
    c.add_argument("--horizon", "-T", type=int_in_range("--horizon", T_MIN, T_MAX), default=DEFAULT_T,
                   help="plan length in steps at 4 FPS")
    c.add_argument("--image-size", type=int_in_range("--image-size", 16, 512), default=84)
    c.add_argument("--pose-error-mm", type=non_negative_float("--pose-error-mm"), default=3.0,
                   help="std of the planner's block position estimate error in the plane (0 = exact)")
    c.add_argument("--pose-error-deg", type=non_negative_float("--pose-error-deg"), default=3.0,
                   help="std of the planner's block yaw estimate error (0 = exact)")
    c.add_argument("--valid-fraction", type=open_unit_fraction("--valid-fraction"), default=None,
                   help="also write a stratified mask/train|valid split with this validation share")
    c.add_argument("--no-progress", action="store_true")

    s = sub.add_parser("serve", help="serve the HTTP API (episodes, plan execution); settings also from FIRP_SIM_* "
                                     "environment variables, which these flags override")
    s.add_argument("--host", default="127.0.0.1")
    s.add_argument("--port", type=int_in_range("--port", 1, 65535), default=8002,
                   help="default 8002 (the scoring service defaults to 8001)")
    s.add_argument("--image-size", type=int_in_range("--image-size", 16, 512), default=None,
                   help="camera image size in px (FIRP_SIM_IMAGE_SIZE, default 84: the datasets' size)")
    s.add_argument("--pose-error-mm", type=non_negative_float("--pose-error-mm"), default=None,
                   help="default pose estimate error in the plane (FIRP_SIM_POSE_ERROR_MM, default 3)")
    s.add_argument("--pose-error-deg", type=non_negative_float("--pose-error-deg"), default=None,
                   help="default yaw estimate error (FIRP_SIM_POSE_ERROR_DEG, default 3)")
    s.add_argument("--max-episodes", type=int_in_range("--max-episodes", 1, 1_000_000), default=None,
                   help="episodes kept at once, oldest evicted (FIRP_SIM_MAX_EPISODES, default 1024)")
    s.add_argument("--episode-ttl-seconds", type=non_negative_float("--episode-ttl-seconds"), default=None,
                   help="episode lifetime (FIRP_SIM_EPISODE_TTL_SECONDS, default 3600)")
    s.add_argument("--log-level", choices=("critical", "error", "warning", "info", "debug"), default="info")
    return parser


def serve(args: argparse.Namespace) -> int:
    import uvicorn
    from pydantic import ValidationError

    from sim_worker.app import create_app
    from sim_worker.settings import SimWorkerSettings

    flags = {"image_size": args.image_size, "pose_error_mm": args.pose_error_mm, "pose_error_deg": args.pose_error_deg,
             "max_episodes": args.max_episodes, "episode_ttl_seconds": args.episode_ttl_seconds}
    try:
        settings = SimWorkerSettings(**{k: v for k, v in flags.items() if v is not None})
    except ValidationError as exc:
        print(f"error: invalid sim worker settings (flags or FIRP_SIM_* variables):\n{exc}", file=sys.stderr)
        return 2
    uvicorn.run(create_app(settings), host=args.host, port=args.port, log_level=args.log_level)
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    if args.command == "serve":
        return serve(args)
    if args.command == "collect":
        from sim_worker.collect import CollectConfig, collect
        from sim_worker.perception import PoseErrorConfig

        error = PoseErrorConfig.from_mm_deg(args.pose_error_mm, args.pose_error_deg)
        config = CollectConfig(task=args.task, episodes=args.episodes, out=args.out, workers=args.workers,
                               seed_offset=args.seed_offset, horizon=args.horizon, image_size=args.image_size,
                               pose_error=error, valid_fraction=args.valid_fraction)
        balance = collect(config, progress=not args.no_progress)
        print(f"{args.out}: {balance['total']} episodes, {balance['success']} success / {balance['failure']} failure "
              f"(success rate {balance['success_rate']:.3f}); {balance['new_episodes']} new in {balance['seconds']} s")
        print(json.dumps(balance))
    return 0


if __name__ == "__main__":
    sys.exit(main())
