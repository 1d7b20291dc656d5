"""Shared fixtures: a real sim worker launched on loopback, and a scripted loopback HTTP stub.

The launcher fixture is session-wide (a sim worker takes a few seconds to start); tests that kill
the worker leave it restarted, so every test reads ``launcher.sim_url`` when it needs it.
"""

from __future__ import annotations

import json
import socket
import threading
import time
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from planner_client.launcher import Launcher


@pytest.fixture(scope="session")
def launcher(tmp_path_factory):
    with Launcher(tmp_path_factory.mktemp("run"), ready_timeout=120) as services:
        yield services


@dataclass
class Seen:
    method: str
    path: str
    headers: dict
    body: object
    at: float


@dataclass
class StubServer:
    """A loopback HTTP server answering from a script of ``(status, json_body[, headers])``; the last entry
    repeats. It records every request it sees, so tests can count retries and read what was sent.
    This is a transport stub for testing the clients' retry behaviour, not a model of any service."""

    script: list[tuple]
    seen: list[Seen] = field(default_factory=list)
    server: ThreadingHTTPServer | None = None

    @property
    def url(self) -> str:
        host, port = self.server.server_address[:2]
        return f"http://{host}:{port}"

    def start(self, sock: socket.socket | None = None) -> "StubServer":
        """Serve on a new loopback port, or on ``sock``: a socket the test bound earlier (see
        :func:`refusing_socket`), so the port it promised a client cannot be taken by anyone else."""
        stub = self

        class Handler(BaseHTTPRequestHandler):
            def _answer(self) -> None:
                length = int(self.headers.get("content-length") or 0)
                raw = self.rfile.read(length) if length else b""
                stub.seen.append(Seen(self.command, self.path, dict(self.headers),
                                      json.loads(raw) if raw else None, time.monotonic()))
                status, body, *extra = stub.script[min(len(stub.seen), len(stub.script)) - 1]
                data = json.dumps(body).encode()
                self.send_response(status)
                for name, value in (extra[0] if extra else {}).items():
                    self.send_header(name, value)
                self.send_header("content-type", "application/json")
                self.send_header("content-length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

            do_GET = do_POST = do_DELETE = _answer

            def log_message(self, *args) -> None:
                pass

        if sock is None:
            self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        else:
            self.server = ThreadingHTTPServer(sock.getsockname(), Handler, bind_and_activate=False)
            self.server.socket.close()
            self.server.socket = sock
            self.server.server_address = sock.getsockname()
            self.server.server_activate()  # listen(): from now on connections are accepted
        threading.Thread(target=self.server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()
        return self

    def stop(self) -> None:
        if self.server is not None:
            self.server.shutdown()
            self.server.server_close()


def refusing_socket() -> socket.socket:
    """A loopback TCP socket bound to a port the OS picked, not listening: connecting to it is refused
    (what a server that is not up yet looks like), and no other process can bind the port meanwhile."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind(("127.0.0.1", 0))
    return sock


@pytest.fixture
def stub():
    """``stub(script)`` starts a scripted loopback server; all are stopped after the test."""
    servers: list[StubServer] = []

    def make(script: list[tuple[int, object]], sock: socket.socket | None = None) -> StubServer:
        servers.append(StubServer(list(script)).start(sock))
        return servers[-1]

    yield make
    for s in servers:
        s.stop()
