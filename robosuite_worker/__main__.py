"""``python -m robosuite_worker serve [--host H] [--port P] [--image-size S] ...`` (also ``firp robosuite``)."""

from __future__ import annotations

import argparse
import os
import sys


def build_parser(prog: str = "python -m robosuite_worker") -> argparse.ArgumentParser:
    from robosuite_worker.settings import RobosuiteSettings
    from world_api.cli import add_serve_parser

    parser = argparse.ArgumentParser(prog=prog, description=__doc__)
    add_serve_parser(parser.add_subparsers(dest="command", required=True), RobosuiteSettings, "robosuite's tasks")
    return parser


def main(argv: list[str] | None = None, prog: str = "python -m robosuite_worker") -> int:
    args = build_parser(prog).parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
    from robosuite_worker.app import create_app
    from robosuite_worker.settings import RobosuiteSettings
    from world_api.cli import serve

    return serve(args, RobosuiteSettings, create_app)


if __name__ == "__main__":
    sys.exit(main())
