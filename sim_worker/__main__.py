"""Command line of the sim worker: ``python -m sim_worker serve ...`` (``collect`` hands over to the planner's)."""

from __future__ import annotations

import argparse
import os
import sys

from firp.core.cli_types import int_in_range, non_negative_float


def build_parser(prog: str = "python -m sim_worker") -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("collect", add_help=False,
                   help="moved to the planner's side (it drives the planner): runs python -m planner_client collect")
    s = sub.add_parser("serve", help="serve the HTTP API (episodes, plan execution); settings also from FIRP_SIM_* "
                                     "environment variables, which these flags override")
    s.add_argument("--host", default=None, help="interface to bind (FIRP_SIM_HOST, default 127.0.0.1)")
    s.add_argument("--port", type=int_in_range("--port", 0, 65535), default=None,
                   help="FIRP_SIM_PORT, default 8002 (the scoring service's is 8001); 0: a free port")
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

    flags = {"host": args.host, "port": args.port, "image_size": args.image_size, "pose_error_mm": args.pose_error_mm, "pose_error_deg": args.pose_error_deg,
             "max_episodes": args.max_episodes, "episode_ttl_seconds": args.episode_ttl_seconds}
    try:
        settings = SimWorkerSettings(**{k: v for k, v in flags.items() if v is not None})
    except ValidationError as exc:
        print(f"error: invalid sim worker settings (flags or FIRP_SIM_* variables):\n{exc}", file=sys.stderr)
        return 2
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level=args.log_level)
    return 0


def main(argv: list[str] | None = None, prog: str = "python -m sim_worker") -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["collect"]:
        # Collection plans, executes and records: it belongs to the side that drives the world, and this
        # package imports no planner. The documented command keeps working by handing over to it.
        print("python -m sim_worker collect: running python -m planner_client collect", file=sys.stderr)
        os.execv(sys.executable, [sys.executable, "-m", "planner_client", *argv])
    args = build_parser(prog).parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    return serve(args)


if __name__ == "__main__":
    sys.exit(main())
