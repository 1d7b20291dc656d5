"""A firp service started as an operator starts it — a real process on loopback — for the tests that
need one (drain on SIGTERM, reload on SIGHUP, logs, the planner's clients against a real server).

The process binds port 0 (the OS picks a free port, which nobody else can take between choosing it and
binding it); the port is read from uvicorn's log line on stderr. Every stderr line is kept, so a test
can assert on the log after the process ended and a failure shows what the process said.
"""

from __future__ import annotations

import os
import queue
import re
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LISTENING = re.compile(r"Uvicorn running on http://127\.0\.0\.1:(\d+)")

__all__ = ["ROOT", "ServedProcess", "clean_env"]


def clean_env(prefix: str, **extra: str) -> dict[str, str]:
    """This process's environment without the service's own settings (``prefix``: ``FIRP_SERVICE_``, …),
    so a developer's exported settings cannot change a test, plus the repository on PYTHONPATH."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(prefix)}
    env.update(PYTHONPATH=str(ROOT), **extra)
    return env


class ServedProcess:
    """``python -m <module> <args>`` with stderr pumped into :attr:`lines`; ``with`` starts it, waits
    until it listens (:attr:`base` is then its URL) and, on leaving, stops it with SIGTERM (SIGKILL if it
    has not exited ``stop_timeout`` seconds later)."""

    def __init__(self, module: str, args: Sequence[str], env: Mapping[str, str], *,
                 listen_timeout: float = 300.0, stop_timeout: float = 60.0, capture_stdout: bool = False):
        self.command = [sys.executable, "-m", module, *args]
        self._stdout = tempfile.TemporaryFile("w+") if capture_stdout else None
        self.env = dict(env)
        self.listen_timeout = listen_timeout
        self.stop_timeout = stop_timeout
        self.lines: list[str] = []
        self._seen: queue.Queue[str | None] = queue.Queue()
        self.proc: subprocess.Popen | None = None
        self._reader: threading.Thread | None = None
        self.base = ""

    @property
    def log(self) -> str:
        return "".join(self.lines)

    @property
    def stdout(self) -> str:
        """What the process printed on standard output (``capture_stdout=True``), so far."""
        if self._stdout is None:
            raise ValueError("started without capture_stdout=True")
        self._stdout.seek(0)
        return self._stdout.read()

    @property
    def returncode(self) -> int | None:
        return None if self.proc is None else self.proc.returncode

    def __enter__(self) -> ServedProcess:
        stdout = subprocess.DEVNULL if self._stdout is None else self._stdout
        self.proc = subprocess.Popen(self.command, cwd=ROOT, env=self.env, stdout=stdout,
                                     stderr=subprocess.PIPE, text=True)
        self._reader = threading.Thread(target=self._pump, daemon=True)
        self._reader.start()
        try:
            self.base = f"http://127.0.0.1:{self._listening_port()}"
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _pump(self) -> None:
        assert self.proc is not None and self.proc.stderr is not None
        for line in self.proc.stderr:
            self.lines.append(line)
            self._seen.put(line)
        self._seen.put(None)

    def _listening_port(self) -> int:
        deadline = time.monotonic() + self.listen_timeout
        while True:
            try:
                line = self._seen.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise AssertionError(f"{' '.join(self.command)} did not listen within {self.listen_timeout:.0f} s:\n"
                                     + self.log) from None
            assert line is not None, f"{' '.join(self.command)} exited before listening:\n" + self.log
            if match := LISTENING.search(line):
                return int(match.group(1))

    def send_signal(self, sig: int) -> None:
        assert self.proc is not None
        self.proc.send_signal(sig)

    def wait(self, timeout: float) -> int:
        """Wait for the process to exit on its own (after a signal); its exit status."""
        assert self.proc is not None
        return self.proc.wait(timeout=timeout)

    def stop(self) -> None:
        """SIGTERM if still running, SIGKILL after ``stop_timeout``; then read stderr to its end."""
        if self.proc is None:
            return
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=self.stop_timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=30)
        if self._reader is not None:
            self._reader.join(timeout=30)
