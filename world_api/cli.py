"""The ``serve`` command line every world worker has: flags that override its ``WorldSettings``, then uvicorn."""

from __future__ import annotations

import argparse
import sys
from typing import Callable

from firp.core.cli_types import int_in_range, non_negative_float
from world_api.settings import WorldSettings

__all__ = ["add_serve_parser", "serve"]

#: flag destination -> settings field (the same names)
_FLAGS = ("host", "port", "image_size", "pose_error_mm", "pose_error_deg", "max_episodes", "episode_ttl_seconds",
          "max_queued", "log_format")


def add_serve_parser(sub: argparse._SubParsersAction, settings: type[WorldSettings], what: str) -> argparse.ArgumentParser:
    """The ``serve`` subcommand of a world whose settings are ``settings`` (the flags' help names its variables)."""
    prefix = settings.model_config["env_prefix"]
    fields = settings.model_fields

    def default(name: str) -> str:
        return f"{prefix}{name.upper()}, default {fields[name].default}"

    s = sub.add_parser("serve", help=f"serve the world API over {what}; settings also from {prefix}* environment "
                                     "variables, which these flags override")
    s.add_argument("--host", default=None, help=f"interface to bind ({default('host')})")
    s.add_argument("--port", type=int_in_range("--port", 0, 65535), default=None,
                   help=f"{default('port')}; 0: a free port")
    s.add_argument("--image-size", type=int_in_range("--image-size", 16, 512), default=None,
                   help=f"camera image size in px ({default('image_size')})")
    s.add_argument("--pose-error-mm", type=non_negative_float("--pose-error-mm"), default=None,
                   help=f"default pose estimate error in the plane ({default('pose_error_mm')})")
    s.add_argument("--pose-error-deg", type=non_negative_float("--pose-error-deg"), default=None,
                   help=f"default yaw estimate error ({default('pose_error_deg')})")
    s.add_argument("--max-episodes", type=int_in_range("--max-episodes", 1, 1_000_000), default=None,
                   help=f"episodes kept at once, oldest evicted ({default('max_episodes')})")
    s.add_argument("--episode-ttl-seconds", type=non_negative_float("--episode-ttl-seconds"), default=None,
                   help=f"episode lifetime ({default('episode_ttl_seconds')})")
    s.add_argument("--max-queued", type=int_in_range("--max-queued", 1, 100_000), default=None,
                   help=f"calls waiting or running at once; one more gets 503 ({default('max_queued')})")
    s.add_argument("--log-level", choices=("critical", "error", "warning", "info", "debug"), default="info")
    s.add_argument("--log-format", choices=("text", "json"), default=None,
                   help=f"json: one JSON object per log line, one line per request ({default('log_format')})")
    return s


def serve(args: argparse.Namespace, settings: type[WorldSettings], create_app: Callable) -> int:
    """Settings from the flags given (the environment fills the rest), then the app under uvicorn; 2 if invalid."""
    import uvicorn
    from pydantic import ValidationError

    given = {name: getattr(args, name) for name in _FLAGS if getattr(args, name, None) is not None}
    try:
        resolved = settings(**given)
    except ValidationError as exc:
        prefix = settings.model_config["env_prefix"]
        print(f"error: invalid settings (flags or {prefix}* variables):\n{exc}", file=sys.stderr)
        return 2
    from firp.core.request_log import configure_logging

    from firp.core.draining import DrainingServer

    from firp.core.tracing import TracingConfigError

    configure_logging(args.log_level, resolved.log_format)
    try:
        app = create_app(resolved)
    except TracingConfigError as exc:  # an OTEL_* variable this install cannot honour
        print(f"error: {exc}", file=sys.stderr)
        return 2

    def begin_drain() -> None:
        app.state.sim.draining = True

    # uvicorn's loggers propagate to the root handler; the request lines are firp.core.request_log's
    config = uvicorn.Config(app, host=resolved.host, port=resolved.port, log_level=args.log_level, access_log=False,
                            log_config=None, timeout_graceful_shutdown=5)
    server = DrainingServer(config, begin_drain=begin_drain, pending=lambda: app.state.sim.runner.pending,
                            grace_s=resolved.drain_grace_s, notice_s=resolved.drain_notice_s)
    server.run()
    return 0 if server.started else 3
