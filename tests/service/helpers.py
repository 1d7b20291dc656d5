"""In-process clients and request builders shared by the service tests.

Why not ``fastapi.testclient.TestClient``: Starlette deprecates it with httpx. The same idea in a
few lines: an event loop in a thread (an anyio blocking portal), the app's lifespan entered there
(or not, to test what the app says before it is ready), and an ``httpx.AsyncClient`` over
``httpx.ASGITransport`` whose calls are made synchronous through the portal.
"""

from __future__ import annotations

import base64
import io
from contextlib import ExitStack
from functools import partial
from typing import Any

import httpx
import numpy as np
from anyio.from_thread import start_blocking_portal
from fastapi import FastAPI
from PIL import Image

from tests.firp.bundle_helpers import random_image, valid_plans

__all__ = ["ServiceClient", "encode_image", "plan_list", "plans_list", "png_b64"]


class ServiceClient:
    """``with ServiceClient(app) as c: c.post(...)``; ``lifespan=False`` leaves the model unloaded."""

    def __init__(self, app: FastAPI, lifespan: bool = True, headers: dict[str, str] | None = None):
        self.app = app
        self.lifespan = lifespan
        self.headers = headers or {}
        self._stack = ExitStack()

    def __enter__(self) -> ServiceClient:
        try:
            self.portal = self._stack.enter_context(start_blocking_portal())
            if self.lifespan:
                self._stack.enter_context(self.portal.wrap_async_context_manager(self.app.router.lifespan_context(self.app)))
            client = httpx.AsyncClient(transport=httpx.ASGITransport(app=self.app), base_url="http://service",
                                       headers=self.headers)
            self.client = self._stack.enter_context(self.portal.wrap_async_context_manager(client))
        except BaseException:
            self._stack.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self._stack.close()

    def request(self, method: str, url: str, **kwargs: Any) -> httpx.Response:
        return self.portal.call(partial(self.client.request, method, url, **kwargs))

    def get(self, url: str, **kwargs: Any) -> httpx.Response:
        return self.request("GET", url, **kwargs)

    def post(self, url: str, **kwargs: Any) -> httpx.Response:
        return self.request("POST", url, **kwargs)


def encode_image(array: np.ndarray, fmt: str = "PNG", **save: Any) -> str:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format=fmt, **save)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def png_b64(size: int = 40, seed: int = 0) -> str:
    return encode_image(random_image(size, seed))


def plan_list(t: int = 10, seed: int = 0) -> list[list[float]]:
    return valid_plans(1, t, seed)[0].tolist()


def plans_list(n: int, t: int = 10, seed: int = 0) -> list[list[list[float]]]:
    return valid_plans(n, t, seed).tolist()
