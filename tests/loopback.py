"""An ASGI app served by a real uvicorn server on loopback, in a thread of the test's own process.

For the tests whose clients need a real socket (Triton's and KServe's clients, the planner client's
httpx calls) but whose assertions need the app's process: spans in an in-memory exporter, the app's
state. The socket is bound here and handed to uvicorn, so no other process can take the port between
choosing and binding it.
"""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

__all__ = ["serve_on_loopback"]


@contextmanager
def serve_on_loopback(app: Any, start_timeout: float = 120.0) -> Iterator[str]:
    """Serve ``app`` (lifespan on) until the block ends; yields ``127.0.0.1:PORT``."""
    import uvicorn

    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", access_log=False, lifespan="on"))
    started = threading.Event()
    real_startup = server.startup

    async def startup(sockets=None):  # noqa: ANN001 - uvicorn's signature
        await real_startup(sockets=sockets)
        started.set()

    server.startup = startup
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    try:
        assert started.wait(start_timeout) and server.started, "the loopback server did not start"
        yield f"127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=30)
        sock.close()
