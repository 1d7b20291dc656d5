"""One error shape for every 4xx/5xx the service sends:

    {"error": {"field": "plan[3][7]", "rule": "one_hot", "message": "..."}}

Why one shape: a planner calling in a loop has to tell "my plan broke rule X at step t" from "my
image is bad" from "the service is not ready" without parsing prose. ``field`` names the offending
part of the request (``null`` when no single part is to blame), ``rule`` is a short stable name a
client may branch on, ``message`` is for humans. FastAPI's own 422s (pydantic), Starlette's
404/405, the contract's :class:`~firp.contract.PlanValidationError` and unexpected exceptions are
all converted into it here.

Every error response also leaves its rule in the ASGI scope (:data:`SCOPE_RULE`) so that the
metrics middleware can count errors by rule without knowing where they came from.
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

from firp.contract import PlanValidationError
from service.schemas import ErrorResponse

__all__ = [
    "SCOPE_RULE",
    "ServiceError",
    "error_content",
    "error_responses",
    "error_response",
    "field_from_loc",
    "install_error_handlers",
]

log = logging.getLogger("service")

#: ASGI scope key under which an error response records its rule (read by service.metrics).
SCOPE_RULE = "firp.error_rule"

_STATUS_RULES = {
    400: "bad_request",
    401: "api_key",
    404: "not_found",
    405: "method_not_allowed",
    413: "max_body_bytes",
    415: "media_type",
    503: "not_ready",
}


class ServiceError(Exception):
    """A request the service refuses: HTTP ``status`` plus the error shape's three fields."""

    def __init__(self, status: int, field: str | None, rule: str, message: str,
                 headers: dict[str, str] | None = None):
        super().__init__(f"{field}: {message} (rule: {rule})")
        self.status = status
        self.field = field
        self.rule = rule
        self.message = message
        self.headers = headers


def error_content(field: str | None, rule: str, message: str) -> dict[str, Any]:
    return {"error": {"field": field, "rule": rule, "message": message}}


def error_response(scope: Scope, status: int, field: str | None, rule: str, message: str,
                   headers: dict[str, str] | None = None) -> JSONResponse:
    """The one error shape as a response; records ``rule`` in ``scope`` for the metrics."""
    scope[SCOPE_RULE] = rule
    return JSONResponse(error_content(field, rule, message), status_code=status, headers=headers)


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


def error_responses(*statuses: int) -> dict[int | str, dict[str, object]]:
    """OpenAPI entries documenting the error shape for ``statuses``."""
    text = {
        400: "the body cannot be framed (binary tensor extension: Inference-Header-Content-Length)",
        401: "X-API-Key missing or wrong (only when an API key is configured)",
        404: "no such model (V2 routes)",
        413: "request body or image too large",
        415: "body is not JSON",
        422: "the request breaks a rule: field and rule are named",
        503: "the model is not loaded and warmed up yet",
    }
    return {s: {"model": ErrorResponse, "description": text[s]} for s in statuses}


async def _service_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ServiceError)
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
    rule = _STATUS_RULES.get(exc.status_code, f"http_{exc.status_code}")
    return error_response(request.scope, exc.status_code, None, rule, str(exc.detail),
                          getattr(exc, "headers", None))


async def _unexpected_error(request: Request, exc: Exception) -> JSONResponse:
    # Starlette calls this from its outermost middleware, after logging nothing: log it here, and
    # tell the client nothing about the internals.
    log.exception("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
    return error_response(request.scope, 500, None, "internal", "internal error; see the service log")


def install_error_handlers(app: FastAPI) -> None:
    app.add_exception_handler(ServiceError, _service_error)
    app.add_exception_handler(PlanValidationError, _plan_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(Exception, _unexpected_error)
