"""A FastAPI route class whose request bodies are parsed by pydantic-core's JSON parser.

Why: a scoring request is mostly numbers (a T = 120 plan is 1,920 floats, ~40 kB of JSON) and
FastAPI parses every JSON body with the standard library's ``json.loads`` before pydantic sees it.
``pydantic_core.from_json`` (Rust, already installed with pydantic) builds the same Python objects
3-6x faster: 0.13 ms instead of 0.47-0.81 ms for a /v1/score body, measured on this project's
2-core CPU (it shares the event loop with every other request, so this is latency for all).

Same results, same refusals: on any input ``from_json`` refuses, the standard parser runs and
decides -- it accepts what it accepts (e.g. lone surrogate escapes) and words the errors as
before, so the 422 ``json_invalid`` answers (with their character offsets) do not change. Where
both accept, they agree (checked in ``tests/service/test_routing.py``: floats to the last bit,
NaN/Infinity, big integers, duplicate keys).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Coroutine
from typing import Any

import pydantic_core
from fastapi.routing import APIRoute
from starlette.requests import Request
from starlette.responses import Response

__all__ = ["FastJSONRequest", "FastJSONRoute", "parse_json"]


def parse_json(body: bytes) -> Any:
    """``json.loads(body)``, computed by pydantic-core where it can (see the module docstring)."""
    try:
        return pydantic_core.from_json(body)
    except ValueError:
        return json.loads(body)  # refused by pydantic-core: the standard parser decides and words it


class FastJSONRequest(Request):
    """A Starlette request whose :meth:`json` uses :func:`parse_json`."""

    async def json(self) -> Any:
        if not hasattr(self, "_json"):
            self._json = parse_json(await self.body())
        return self._json


class FastJSONRoute(APIRoute):
    """An ``APIRoute`` handing its endpoint a :class:`FastJSONRequest` (FastAPI's documented way
    to customise the request class of a router's routes)."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def route_handler(request: Request) -> Response:
            return await handler(FastJSONRequest(request.scope, request.receive))

        return route_handler
