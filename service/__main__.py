"""``python -m service [--host H] [--port P] [--bundle DIR] [--task NAME] [--threads N]``

Flags map onto :class:`service.settings.ServiceSettings`; anything not given comes from the
``FIRP_SERVICE_*`` environment, then from the defaults. One uvicorn process, one model: scale out
with more processes (each loads the bundle) rather than more threads per request.

Exit status: 2 for bad flags or settings; 3 (uvicorn's) when the application fails to start,
e.g. a missing, corrupt or incompatible bundle -- the log names the file and the rule. On SIGTERM the
service drains (:mod:`service.server`: readiness 503 at once, admitted work answered within
``drain_grace_s``) and exits 0; Ctrl-C (or a second SIGTERM) stops at once, uvicorn's way (130).
SIGHUP swaps in the configured bundle's directory, read again, without dropping a request.
"""

from __future__ import annotations

import argparse
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
    ap.add_argument("--log-format", choices=["text", "json"],
                    help="json: one JSON object per log line, one line per request (default text; env "
                         "FIRP_SERVICE_LOG_FORMAT)")
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

    from firp.core.request_log import configure_logging
    from service.app import create_app
    from service.server import ServiceServer

    from firp.core.tracing import TracingConfigError

    configure_logging(settings.log_level, settings.log_format)
    try:
        app = create_app(settings)
    except TracingConfigError as exc:  # an OTEL_* variable this install cannot honour
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    # uvicorn's loggers propagate to the root handler; the request lines are firp.core.request_log's
    config = uvicorn.Config(app, host=settings.host, port=settings.port, log_level=settings.log_level,
                            access_log=False, log_config=None, timeout_graceful_shutdown=5)
    server = ServiceServer(config, app, settings.drain_grace_s, settings.drain_notice_s)
    server.run()
    if not server.started:  # the lifespan failed (the log says why): uvicorn's start-up failure status
        return 3
    return 0


if __name__ == "__main__":
    sys.exit(main())
