"""One HTTP server as a local subprocess: a free loopback port, a log file, readiness, stop, restart.

The launcher runs the scoring service and the sim worker this way. Everything that can go wrong at
start-up says which server, which URL and why, with the last lines of the server's log -- a
process that dies at import time is otherwise just a "connection refused".
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Mapping, Sequence

import httpx


class ServerStartError(RuntimeError):
    """A server exited or stayed unready during start-up; the message carries its log's tail."""


def free_port(host: str = "127.0.0.1") -> int:
    """A port the OS says is free now. Another process may still take it before the server binds,
    which :meth:`ManagedServer.start` detects (the server exits) and answers with another port."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def _die_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    """Linux: SIGTERM the server when its parent dies, so a killed run leaves no orphan servers.

    The kernel ties this to the *thread* that forked, so it is only set for servers started from
    the main thread (whose end is the process's end); a server started from a worker thread must
    not die when that thread finishes."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def _death_signal_hook() -> Callable[[], None] | None:
    on_main_thread = threading.current_thread() is threading.main_thread()
    return _die_with_parent if sys.platform == "linux" and on_main_thread else None


class ManagedServer:
    """``command(port)`` gives the server's argv; it is ready when ``GET ready_path`` answers 200."""

    def __init__(self, name: str, command: Callable[[int], Sequence[str]], log_dir: Path, *,
                 host: str = "127.0.0.1", ready_path: str = "/readyz", ready_timeout: float = 120.0,
                 stop_timeout: float = 10.0, env: Mapping[str, str] | None = None, port_attempts: int = 3):
        self.name = name
        self.command = command
        self.host = host
        self.ready_path = ready_path
        self.ready_timeout = ready_timeout
        self.stop_timeout = stop_timeout
        self.env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
        self.port_attempts = port_attempts
        log_dir.mkdir(parents=True, exist_ok=True)
        self.log_path = log_dir / f"{name.replace(' ', '_')}.log"
        self.process: subprocess.Popen | None = None
        self.port: int | None = None
        self.starts = 0  # how many processes were started (restarts included)
        self._log_offset = 0

    @property
    def url(self) -> str:
        if self.port is None:
            raise RuntimeError(f"{self.name} is not started")
        return f"http://{self.host}:{self.port}"

    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    # -- start ------------------------------------------------------------------------------
    def spawn(self) -> None:
        """Start the process on a fresh free port, output appended to the log (does not wait)."""
        self.port = free_port(self.host)
        argv = [str(a) for a in self.command(self.port)]
        with self.log_path.open("ab") as log:
            self._log_offset = log.tell()
            log.write(f"\n=== {time.strftime('%Y-%m-%d %H:%M:%S')} start {self.name} on port {self.port}: "
                      f"{' '.join(argv)}\n".encode())
            log.flush()
            self.process = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                            env=self.env, preexec_fn=_death_signal_hook())
        self.starts += 1

    def wait_ready(self) -> None:
        """Poll until ready; raise :class:`ServerStartError` if the process exits or time runs out."""
        assert self.process is not None, "spawn() first"
        deadline = time.monotonic() + self.ready_timeout
        last = "no answer yet"
        with httpx.Client(timeout=2.0) as client:
            while True:
                code = self.process.poll()
                if code is not None:
                    raise ServerStartError(f"{self.name} exited with code {code} before it was ready at {self.url}; "
                                           f"last lines of {self.log_path}:\n{self.log_tail()}")
                try:
                    response = client.get(self.url + self.ready_path)
                    if response.status_code == 200:
                        return
                    last = f"HTTP {response.status_code}: {response.text[:200]}"
                except httpx.TransportError as exc:
                    last = type(exc).__name__
                if time.monotonic() > deadline:
                    self.stop()
                    raise ServerStartError(f"{self.name} was not ready at {self.url}{self.ready_path} within "
                                           f"{self.ready_timeout:g} s (last: {last}); stopped it. Last lines of "
                                           f"{self.log_path}:\n{self.log_tail()}")
                time.sleep(0.1)

    def start(self) -> str:
        """Spawn and wait until ready, on a new port if another process took the chosen one."""
        for attempt in range(1, self.port_attempts + 1):
            self.spawn()
            try:
                self.wait_ready()
                return self.url
            except ServerStartError:
                if attempt == self.port_attempts or "address already in use" not in self.log_tail().lower():
                    raise
        raise AssertionError("unreachable")

    # -- stop -------------------------------------------------------------------------------
    def stop(self) -> None:
        """SIGTERM (a graceful shutdown), then SIGKILL after ``stop_timeout`` seconds."""
        process, self.process = self.process, None
        if process is None or process.poll() is not None:
            return
        process.terminate()
        try:
            process.wait(self.stop_timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()

    def restart(self) -> str:
        """Stop (if still running) and start again on a new port; returns the new URL."""
        self.stop()
        return self.start()

    def log_tail(self, lines: int = 30) -> str:
        """The last ``lines`` lines this process wrote (earlier runs in the same log are skipped)."""
        try:
            with self.log_path.open("rb") as log:
                log.seek(self._log_offset)
                text = log.read().decode(errors="replace")
        except OSError:
            return "(no log)"
        return "\n".join(text.rstrip().splitlines()[-lines:]) or "(empty log)"
