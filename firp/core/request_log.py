"""Request ids and one structured log line per request, for every firp HTTP API.

Why: a planner's trial calls the scoring service and the sim worker many times; when a trial goes
wrong, an operator needs to find *its* calls in both services' logs. So every request carries an
``X-Request-ID`` -- the caller's (the planner client sends one per trial and stores it in the trial's
record), or one generated here -- which is echoed in the response and written on the request's log
line. With JSON logs on (``log_format = "json"``), that line is one JSON object per request::

    {"time": "2026-12-02T01:02:03.456Z", "level": "info", "logger": "service.access",
     "request_id": "trial-3-9f2c1a7e04b1", "method": "POST", "route": "/v1/score", "status": 200,
     "latency_ms": 9.8, "model_version": "3b2f0c1d9e8a", "plans": 1}

``route`` is the route's template (``/v1/episodes/{episode_id}/execute``), as in the metrics; a
route may add fields by writing into ``scope["firp.log"]`` (the scoring service adds the model
version and the number of plans). Other log records become JSON objects too
(:class:`JsonFormatter`), so the stream stays one object per line.

A malformed ``X-Request-ID`` (more than 128 characters, or characters outside ``A-Z a-z 0-9 . _ : / -``)
is refused with 400 naming the header: it would otherwise be written into logs verbatim.
"""

from __future__ import annotations

import json
import logging
import re
import sys
import time
import uuid
from datetime import datetime, timezone
from typing import Any

from starlette.datastructures import Headers, MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from firp.core.http_errors import error_response

__all__ = ["JsonFormatter", "REQUEST_ID_HEADER", "RequestLog", "SCOPE_LOG", "SCOPE_REQUEST_ID", "configure_logging"]

REQUEST_ID_HEADER = "X-Request-ID"
SCOPE_REQUEST_ID = "firp.request_id"
SCOPE_LOG = "firp.log"  # extra fields of the request's log line
_VALID_ID = re.compile(r"[A-Za-z0-9._:/-]{1,128}")


def _utc(seconds: float) -> str:
    return datetime.fromtimestamp(seconds, tz=timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


class JsonFormatter(logging.Formatter):
    """A log record as one JSON object: time, level, logger, message, and the record's ``fields``."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {"time": _utc(record.created), "level": record.levelname.lower(), "logger": record.name}
        fields = getattr(record, "fields", None)
        if fields:
            out.update(fields)
        else:
            out["message"] = record.getMessage()
        if record.exc_info:
            out["exception"] = self.formatException(record.exc_info)
        return json.dumps(out, default=str)


def configure_logging(level: str, log_format: str) -> None:
    """The process's root handler: text, or one JSON object per line (``json``). uvicorn is then run
    with ``log_config=None``, so its own loggers propagate here, and without its access log (the
    request lines of :class:`RequestLog` replace it)."""
    handler = logging.StreamHandler(sys.stderr)
    if log_format == "json":
        handler.setFormatter(JsonFormatter())
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())


class RequestLog:
    """Pure ASGI middleware: the request id (accepted or generated, echoed) and the request's log line."""

    def __init__(self, app: ASGIApp, logger: str, enabled: bool = True):
        self.app = app
        self.log = logging.getLogger(logger)
        self.enabled = enabled

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        given = Headers(scope=scope).get(REQUEST_ID_HEADER)
        request_id = given if given is not None else uuid.uuid4().hex
        status = 500

        async def send_with_id(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
                MutableHeaders(scope=message).append(REQUEST_ID_HEADER, request_id)
            await send(message)

        scope[SCOPE_REQUEST_ID] = request_id
        scope[SCOPE_LOG] = {}
        try:
            if given is not None and not _VALID_ID.fullmatch(given):
                request_id = uuid.uuid4().hex  # the refused one is not echoed into headers or logs
                scope[SCOPE_REQUEST_ID] = request_id
                await error_response(scope, 400, REQUEST_ID_HEADER, "request_id",
                                     f"{REQUEST_ID_HEADER} must be 1-128 characters of A-Z a-z 0-9 . _ : / - "
                                     f"(got {len(given)} characters)")(scope, receive, send_with_id)
                return
            await self.app(scope, receive, send_with_id)
        finally:
            if self.enabled:
                route = getattr(scope.get("route"), "path", None) or scope.get("path", "")
                fields = {"request_id": request_id, "method": scope.get("method"), "route": route, "status": status,
                          "latency_ms": round((time.perf_counter() - start) * 1000.0, 3), **scope[SCOPE_LOG]}
                self.log.info("%s %s %s %d %.1f ms", request_id, scope.get("method"), route, status,
                              fields["latency_ms"], extra={"fields": fields})
