"""One error shape for every 4xx/5xx: ``{"error": {"field": ..., "rule": ..., "message": ...}}``.

Clients branch on ``rule`` (machine-readable) and show ``message``; ``field`` says which input to
fix. FastAPI's own 422s, Starlette's 404/405s and the plan contract's errors are all translated
into this shape, so a client never has to parse two formats.
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from firp.contract import PlanValidationError

log = logging.getLogger("sim_worker")

_STATUS_RULES = {400: "bad_request", 404: "not_found", 405: "method_not_allowed", 415: "unsupported_media_type"}


class ApiError(Exception):
    """An error the API reports on purpose, with its status, field and rule."""

    def __init__(self, status: int, field: str | None, rule: str, message: str):
        super().__init__(message)
        self.status = status
        self.field = field
        self.rule = rule
        self.message = message


def error_response(status: int, field: str | None, rule: str, message: str) -> JSONResponse:
    return JSONResponse({"error": {"field": field, "rule": rule, "message": message}}, status_code=status)


def field_path(loc: tuple) -> str | None:
    """A pydantic error location as the contract writes fields: ``('body', 'plan', 3)`` -> ``plan[3]``."""
    parts = list(loc[1:]) if loc and loc[0] in ("body", "query", "path") else list(loc)
    out = ""
    for part in parts:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or (str(loc[0]) if loc else None)


def _validation_error(_: Request, exc: RequestValidationError) -> JSONResponse:
    first = exc.errors()[0]
    rule = first.get("type", "invalid")
    field = "body" if rule == "json_invalid" else field_path(tuple(first.get("loc", ())))
    message = first.get("msg", "invalid request")
    more = len(exc.errors()) - 1
    if more:
        message += f" (and {more} more error{'s' if more > 1 else ''})"
    return error_response(422, field, rule, message)


def _plan_error(_: Request, exc: PlanValidationError) -> JSONResponse:
    return error_response(422, exc.field, exc.rule, exc.detail)


def _api_error(_: Request, exc: ApiError) -> JSONResponse:
    return error_response(exc.status, exc.field, exc.rule, exc.message)


def _http_error(_: Request, exc: StarletteHTTPException) -> JSONResponse:
    rule = _STATUS_RULES.get(exc.status_code, f"http_{exc.status_code}")
    return error_response(exc.status_code, None, rule, str(exc.detail))


def _unexpected(_: Request, exc: Exception) -> JSONResponse:
    log.exception("unhandled error", exc_info=exc)
    return error_response(500, None, "internal_error", f"{type(exc).__name__}: {exc}")


def install_error_handlers(app: FastAPI) -> None:
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(PlanValidationError, _plan_error)
    app.add_exception_handler(ApiError, _api_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(Exception, _unexpected)
