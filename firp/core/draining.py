"""Drain on SIGTERM for every firp HTTP service: stop taking work at once, finish what was taken,
exit 0 within a grace period.

Why not uvicorn's own SIGTERM handling: it closes the listening socket at once (a load balancer's
readiness probe then sees connection errors, not a clean "not ready") and re-raises the signal after
shutdown, so the process ends with status -15, which a supervisor reads as a crash. An orchestrator
(compose's ``stop_grace_period``, Kubernetes' ``terminationGracePeriodSeconds``) sends SIGTERM, waits,
then SIGKILLs; a service that is boring to operate uses that time like this:

1. **At once** (``begin_drain``): readiness answers 503 ``draining`` and new work is refused with
   503 ``not_ready`` and ``Retry-After`` (a client retries on another replica).
2. **Drain:** work already admitted is answered, for at most ``grace_s`` (shorter than the
   orchestrator's grace period); the socket stays open at least ``notice_s``, so a balancer's probe
   sees the 503 even when the service is idle.
3. **Stop:** uvicorn's normal shutdown (connections closed, the lifespan's shutdown), exit status 0.

A second SIGTERM, or SIGINT (Ctrl-C), stops at once as uvicorn always does.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import time
from collections.abc import Callable
from types import FrameType

import uvicorn

__all__ = ["DrainingServer"]

POLL_S = 0.02


class DrainingServer(uvicorn.Server):
    """uvicorn's server with the drain above on the first SIGTERM.

    ``begin_drain()`` flips the app to draining; ``pending()`` counts the work still to answer."""

    def __init__(self, config: uvicorn.Config, *, begin_drain: Callable[[], None], pending: Callable[[], int],
                 grace_s: float, notice_s: float = 0.0, log: logging.Logger | None = None):
        super().__init__(config)
        self.begin_drain = begin_drain
        self.pending = pending
        self.grace_s = grace_s
        self.notice_s = notice_s
        self.log = log or logging.getLogger("uvicorn.error")
        self.draining = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._drain_task: asyncio.Task | None = None

    async def serve(self, sockets=None) -> None:  # noqa: ANN001 - uvicorn's signature
        self._loop = asyncio.get_running_loop()
        await super().serve(sockets)

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        if sig != signal.SIGTERM or self.draining or self._loop is None:
            super().handle_exit(sig, frame)
            return
        # not appended to uvicorn's captured signals: they would be re-raised after shutdown (status -15)
        self.draining = True
        self.begin_drain()
        self._loop.call_soon_threadsafe(self._start_drain)

    def _start_drain(self) -> None:
        self._drain_task = asyncio.ensure_future(self._drain())

    async def _drain(self) -> None:
        start = time.monotonic()
        self.log.info("SIGTERM: draining (%d pending; grace %.1f s)", self.pending(), self.grace_s)
        while time.monotonic() - start < self.grace_s and (self.pending()
                                                           or time.monotonic() - start < self.notice_s):
            await asyncio.sleep(POLL_S)
        left = self.pending()
        if left:
            self.log.warning("drain: grace of %.1f s over with %d still pending; stopping", self.grace_s, left)
        else:
            self.log.info("drained in %.0f ms; stopping", (time.monotonic() - start) * 1000)
        self.should_exit = True
