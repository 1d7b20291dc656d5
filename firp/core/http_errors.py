"""The one error shape of every firp HTTP API (the scoring service and the sim worker):

    {"error": {"field": "plan[3][7]", "rule": "one_hot", "message": "..."}}

Why one shape, and why here: a planner calls both services in one loop and has to tell "my plan
broke rule X at step t" from "my image is bad" from "the service is not ready" without parsing
prose, whichever service answered. ``field`` names the offending part of the request (``null`` when
no single part is to blame), ``rule`` is a short stable name a client may branch on, ``message`` is
for humans. It sits beside :mod:`firp.core.contract`, whose :class:`~firp.core.contract.PlanValidationError`
both services report through it; it needs FastAPI but neither torch nor mujoco, so each service
imports it without the other's heavy dependencies.

The Open Inference Protocol (V2) specifies its own error body, ``{"error": "<message>"}``, which V2
clients (Triton's, KServe's) read: on the ``/v2`` routes the message is the ``error`` string and
``field`` and ``rule`` stand beside it, so the same three facts reach every client.

FastAPI's own 422s (pydantic), Starlette's 404/405, the contract's plan errors, :class:`ApiError`
raised by a route and unexpected exceptions are all converted into the shape by
:func:`install_error_handlers`. Every error response also records its rule in the ASGI scope
(:data:`SCOPE_RULE`) so that a metrics middleware can count errors by rule.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import Scope

from firp.core.contract import PlanValidationError

__all__ = ["SCOPE_RULE", "STATUS_RULES", "V2_PREFIX", "ApiError", "error_content", "error_response", "field_from_loc",
           "install_error_handlers"]

#: ASGI scope key under which an error response records its rule (read by service.metrics).
SCOPE_RULE = "firp.error_rule"

#: The rule of an error that has nothing but an HTTP status (Starlette's own 404/405, middleware).
STATUS_RULES = {
    400: "bad_request",
    401: "api_key",
    404: "not_found",
    405: "method_not_allowed",
    413: "max_body_bytes",
    415: "media_type",
    503: "not_ready",
}


#: Paths under this prefix answer errors in the V2 protocol's shape.
V2_PREFIX = "/v2"


class ApiError(Exception):
    """A request an API refuses on purpose: HTTP ``status`` plus the error shape's three fields."""

    def __init__(self, status: int, field: str | None, rule: str, message: str,
                 headers: dict[str, str] | None = None):
        super().__init__(f"{field}: {message} (rule: {rule})")
        self.status = status
        self.field = field
        self.rule = rule
        self.message = message
        self.headers = headers


def error_content(field: str | None, rule: str, message: str, v2: bool = False) -> dict[str, Any]:
    """The error body: ``{"error": {field, rule, message}}``, or on V2 routes
    ``{"error": message, "field": ..., "rule": ...}``."""
    if v2:
        return {"error": message, "field": field, "rule": rule}
    return {"error": {"field": field, "rule": rule, "message": message}}


def is_v2_path(path: str) -> bool:
    return path == V2_PREFIX or path.startswith(V2_PREFIX + "/")


def error_response(scope: Scope | None, status: int, field: str | None, rule: str, message: str,
                   headers: dict[str, str] | None = None) -> JSONResponse:
    """The error shape of the request's route as a response; records ``rule`` in ``scope`` (when
    given) for metrics."""
    v2 = False
    if scope is not None:
        scope[SCOPE_RULE] = rule
        v2 = is_v2_path(scope.get("path", ""))
    return JSONResponse(error_content(field, rule, message, v2), status_code=status, headers=headers)


def field_from_loc(loc: Sequence[str | int]) -> str:
    """pydantic's ``("body", "plan", 3, 7)`` -> ``"plan[3][7]"`` (the request part is dropped
    unless it is all there is: ``("body",)`` -> ``"body"``)."""
    parts = list(loc)
    if len(parts) > 1 and parts[0] in ("body", "query", "path", "header", "cookie"):
        parts = parts[1:]
    out = ""
    for p in parts:
        if isinstance(p, int):
            out += f"[{p}]"
        else:
            out += f".{p}" if out else str(p)
    return out


async def _api_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ApiError)
    return error_response(request.scope, exc.status, exc.field, exc.rule, exc.message, exc.headers)


async def _plan_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, PlanValidationError)
    return error_response(request.scope, 422, exc.field, exc.rule, exc.detail)


async def _validation_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    errors = exc.errors()
    if not errors:  # pragma: no cover - FastAPI always gives at least one
        return error_response(request.scope, 422, None, "invalid", "the request is invalid")
    first = errors[0]
    rule = str(first.get("type", "invalid"))
    message = str(first.get("msg", "invalid value"))
    field = field_from_loc(first.get("loc", ()))
    if rule == "json_invalid":  # loc is ("body", <character offset>): say where in the message
        field = "body"
        message = f"{message} at character {first['loc'][-1]}: {first.get('ctx', {}).get('error', '')}".rstrip(": ")
    if len(errors) > 1:
        message += f" (and {len(errors) - 1} more problem{'s' if len(errors) > 2 else ''})"
    return error_response(request.scope, 422, field, rule, message)


async def _http_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    rule = STATUS_RULES.get(exc.status_code, f"http_{exc.status_code}")
    return error_response(request.scope, exc.status_code, None, rule, str(exc.detail),
                          getattr(exc, "headers", None))


def install_error_handlers(app: FastAPI, log: logging.Logger) -> None:
    """Route every error of ``app`` into the one shape; unexpected exceptions are logged to ``log``
    with their traceback, and the client learns nothing about the internals (500 ``internal``)."""

    async def unexpected_error(request: Request, exc: Exception) -> JSONResponse:
        # Starlette calls this from its outermost middleware, after logging nothing: log it here.
        log.exception("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
        return error_response(request.scope, 500, None, "internal", f"internal error; see the {log.name} log")

    app.add_exception_handler(ApiError, _api_error)
    app.add_exception_handler(PlanValidationError, _plan_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(Exception, unexpected_error)
