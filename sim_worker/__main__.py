"""Command line of the sim worker: ``python -m sim_worker serve ...`` (``collect`` hands over to the planner's)."""

from __future__ import annotations

import argparse
import os
import sys


def build_parser(prog: str = "python -m sim_worker") -> argparse.ArgumentParser:
    from sim_worker.settings import SimWorkerSettings
    from world_api.cli import add_serve_parser

    parser = argparse.ArgumentParser(prog=prog, description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("collect", add_help=False,
                   help="moved to the planner's side (it drives the planner): runs python -m planner_client collect")
    add_serve_parser(sub, SimWorkerSettings, "our MuJoCo world")
    return parser


def main(argv: list[str] | None = None, prog: str = "python -m sim_worker") -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["collect"]:
        # Collection plans, executes and records: it belongs to the side that drives the world, and this
        # package imports no planner. The documented command keeps working by handing over to it.
        print("python -m sim_worker collect: running python -m planner_client collect", file=sys.stderr)
        os.execv(sys.executable, [sys.executable, "-m", "planner_client", *argv])
    args = build_parser(prog).parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    from sim_worker.app import create_app
    from sim_worker.settings import SimWorkerSettings
    from world_api.cli import serve

    return serve(args, SimWorkerSettings, create_app)


if __name__ == "__main__":
    sys.exit(main())
