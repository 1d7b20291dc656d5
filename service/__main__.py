"""``python -m service [--host H] [--port P] [--bundle DIR] [--task NAME] [--threads N]``

Flags map onto :class:`service.settings.ServiceSettings`; anything not given comes from the
``FIRP_SERVICE_*`` environment, then from the defaults. One uvicorn process, one model: scale out
with more processes (each loads the bundle) rather than more threads per request.

Exit status: 2 for bad flags or settings; 3 (uvicorn's) when the application fails to start,
e.g. a missing, corrupt or incompatible bundle -- the log names the file and the rule. On SIGTERM or
Ctrl-C uvicorn finishes the requests in flight, runs the lifespan's shutdown, and exits by that
signal (status -15 / 130 as a shell sees it).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from pydantic import ValidationError

from service.settings import ServiceSettings

__all__ = ["main", "parse_args"]


def parse_args(argv: list[str] | None = None, prog: str = "python -m service") -> dict[str, object]:
    """Only the flags that were given, as settings fields (so the environment fills the rest)."""
    ap = argparse.ArgumentParser(prog=prog, description="FIRP plan scoring service (FastAPI/uvicorn)")
    ap.add_argument("--host", help="interface to bind (default 127.0.0.1; env FIRP_SERVICE_HOST)")
    ap.add_argument("--port", type=int, help="port (default 8001; env FIRP_SERVICE_PORT)")
    ap.add_argument("--bundle", type=Path, help="bundle directory (default: the shipped bundle of --task; "
                                                "env FIRP_SERVICE_BUNDLE)")
    ap.add_argument("--task", help="task whose shipped bundle to load (default stacking; env FIRP_SERVICE_TASK)")
    ap.add_argument("--threads", type=int, help="torch threads for inference (default 1; env FIRP_SERVICE_THREADS)")
    ap.add_argument("--log-level", choices=["critical", "error", "warning", "info", "debug"],
                    help="log level (default info)")
    ap.add_argument("--no-access-log", dest="access_log", action="store_const", const=False,
                    help="do not log every request")
    args = vars(ap.parse_args(argv))
    return {k: v for k, v in args.items() if v is not None}


def main(argv: list[str] | None = None, prog: str = "python -m service") -> int:
    overrides = parse_args(argv, prog)
    try:
        settings = ServiceSettings(**overrides)
    except ValidationError as exc:
        print(f"{prog}: invalid settings:\n{exc}", file=sys.stderr)
        return 2
    import uvicorn  # after the settings are known to be good: a typo should not wait for torch

    from service.app import create_app

    logging.basicConfig(level=settings.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level=settings.log_level,
                access_log=settings.access_log)
    return 0


if __name__ == "__main__":
    sys.exit(main())
