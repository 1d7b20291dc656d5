"""Command line of the sim worker: ``python -m sim_worker collect ...``."""

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
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    if args.command == "collect":
        from sim_worker.collect import CollectConfig, collect
        from sim_worker.perception import PoseErrorConfig

        error = PoseErrorConfig(xy_std=args.pose_error_mm / 1000.0, z_std=min(args.pose_error_mm, 1.0) / 1000.0,
                                yaw_std_deg=args.pose_error_deg)
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
