"""The scoring service's errors: the one shape of :mod:`firp.core.http_errors` (shared with the sim
worker), plus the OpenAPI entries that document it for the service's routes.

    {"error": {"field": "plan[3][7]", "rule": "one_hot", "message": "..."}}

and on the V2 routes the protocol's ``{"error": "...", "field": "plan[3][7]", "rule": "one_hot"}``.

``ServiceError`` is the shared :class:`~firp.core.http_errors.ApiError` under the name the service's
modules use; every error response records its rule in the ASGI scope (``SCOPE_RULE``) for
:mod:`service.metrics`.
"""

from __future__ import annotations

import logging

from fastapi import FastAPI

from firp.core import http_errors
from firp.core.http_errors import SCOPE_RULE, error_content, error_response, field_from_loc
from firp.core.http_errors import ApiError as ServiceError
from service.schemas import ErrorResponse, V2ErrorResponse

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


def error_responses(*statuses: int, v2: bool = False) -> dict[int | str, dict[str, object]]:
    """OpenAPI entries documenting the error shape (V2's on the ``/v2`` routes) for ``statuses``."""
    text = {
        400: "a header is malformed (X-Request-Timeout), or the body cannot be framed (binary tensor "
             "extension: Inference-Header-Content-Length)",
        401: "X-API-Key missing or wrong (only when an API key is configured)",
        404: "no such model (V2 routes)",
        413: "request body or image too large",
        415: "body is not JSON",
        422: "the request breaks a rule: field and rule are named",
        503: "the model is not loaded and warmed up yet (not_ready), or the service is full (overloaded): "
             "retry after Retry-After seconds",
        504: "the request's time budget (X-Request-Timeout, V2 parameters.timeout, or the default) ran out "
             "before it was scored (deadline_exceeded)",
    }
    model = V2ErrorResponse if v2 else ErrorResponse
    return {s: {"model": model, "description": text[s]} for s in statuses}


def install_error_handlers(app: FastAPI) -> None:
    http_errors.install_error_handlers(app, log)
