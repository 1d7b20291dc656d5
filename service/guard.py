"""Refuse oversized bodies (413), non-JSON bodies (415) and non-UTF-8 bodies before any route reads them.

Why a middleware and not a dependency: a dependency runs after FastAPI has read and parsed the
whole body; the limit must hold while the body is being *received*, chunk by chunk, and a body
with a wrong content type must not be parsed at all (FastAPI would otherwise treat it as bytes
and answer with a confusing 422). JSON between systems is UTF-8 (RFC 8259); FastAPI would answer
other bytes with a bare 400. All answers use the service's one error shape.

The V2 repository's routes (optional bodies) take a body without a Content-Type as JSON, as
Triton's client sends it.

Only requests that a route will take (path *and* method match) are guarded: a PUT to a POST-only
path, or any request to an unknown path, goes on to the router for its 405/404, unread.

The V2 inference routes (``binary_routes``) also take the KServe/Triton binary tensor extension:
a body framed by an ``Inference-Header-Content-Length`` header (a JSON header, then raw tensor
bytes) may have any content type and is not UTF-8; a body without that header may come without a
Content-Type (Triton's clients send none) and is then read as JSON. The framing itself is checked
by the route (:mod:`service.v2`). The size limit holds for every body.
"""

from __future__ import annotations

from collections.abc import Sequence

from starlette.datastructures import Headers
from starlette.routing import BaseRoute, Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.errors import error_response

__all__ = ["BINARY_HEADER", "RequestGuard", "is_json_media_type"]

_BODY_METHODS = ("POST", "PUT", "PATCH")
#: The binary tensor extension's header: the length of the JSON header at the start of the body.
BINARY_HEADER = "Inference-Header-Content-Length"


def is_json_media_type(content_type: str | None) -> bool:
    """``application/json`` or ``application/<x>+json``, parameters (charset) allowed."""
    if not content_type:
        return False
    media = content_type.split(";", 1)[0].strip().lower()
    return media == "application/json" or (media.startswith("application/") and media.endswith("+json"))


class RequestGuard:
    """Pure ASGI middleware: content type and body size for requests that carry a body."""

    def __init__(self, app: ASGIApp, max_body_bytes: int, routes: Sequence[BaseRoute],
                 binary_routes: Sequence[BaseRoute] = (), optional_body_routes: Sequence[BaseRoute] = ()):
        self.app = app
        self.max_body_bytes = max_body_bytes
        self.routes = tuple(routes)
        self.binary_routes = tuple(binary_routes)
        self.optional_body_routes = tuple(optional_body_routes)  # a body without Content-Type is JSON

    def _routed(self, scope: Scope) -> bool:
        return any(route.matches(scope)[0] == Match.FULL for route in self.routes)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] not in _BODY_METHODS or not self._routed(scope):
            await self.app(scope, receive, send)
            return
        headers = Headers(scope=scope)
        content_type = headers.get("content-type")
        v2 = any(route.matches(scope)[0] == Match.FULL for route in self.binary_routes)
        binary = v2 and BINARY_HEADER in headers
        # V2 clients (Triton's) send the repository's small JSON bodies, or none, without a Content-Type
        optional = content_type is None and any(
            route.matches(scope)[0] == Match.FULL for route in self.optional_body_routes)
        if not (binary or optional or is_json_media_type(content_type) or (v2 and content_type is None)):
            got = repr(content_type) if content_type else "no Content-Type"
            await error_response(scope, 415, "Content-Type", "media_type",
                                 f"the body must be JSON (Content-Type: application/json), got {got}")(scope, receive, send)
            return
        declared = headers.get("content-length")
        if declared is not None:
            if not declared.isdigit():
                await error_response(scope, 400, "Content-Length", "content_length",
                                     f"Content-Length must be a non-negative integer, got {declared!r}")(scope, receive, send)
                return
            if int(declared) > self.max_body_bytes:
                await self._too_large(scope, receive, send)
                return
        # Read the body here, counting: a chunked body has no Content-Length to check up front.
        chunks: list[bytes] = []
        size = 0
        more = True
        while more:
            message = await receive()
            if message["type"] == "http.disconnect":
                return  # the client went away; nothing to answer
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > self.max_body_bytes:
                await self._too_large(scope, receive, send)
                return
            chunks.append(chunk)
            more = message.get("more_body", False)
        body = b"".join(chunks)
        try:
            if not binary:  # a binary body's JSON header is checked by its route
                body.decode("utf-8")
        except UnicodeDecodeError as exc:
            await error_response(scope, 422, "body", "json_invalid",
                                 f"the body is not UTF-8 text ({exc.reason} at byte {exc.start})")(scope, receive, send)
            return
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()  # after the body: wait for the disconnect, as a server would

        await self.app(scope, replay, send)

    async def _too_large(self, scope: Scope, receive: Receive, send: Send) -> None:
        await error_response(scope, 413, "body", "max_body_bytes",
                             f"the request body is larger than {self.max_body_bytes} bytes")(scope, receive, send)
