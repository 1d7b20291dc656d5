"""The service's process: uvicorn's server with two signals of its own -- SIGTERM drains, SIGHUP reloads.

**SIGHUP** swaps in the configured bundle's directory, read again (:meth:`service.repository.
ModelRepository.reload`: load, verify, warm off the serving path, switch; a failure keeps the old
model and is logged).

**SIGTERM** drains: stop taking work at once, finish what was taken, exit 0 within a grace period.

Why not uvicorn's own SIGTERM handling: it closes the listening socket at once (a load balancer's
readiness probe then sees connection errors, not a clean "not ready") and re-raises the signal after
shutdown, so the process ends with status -15, which a supervisor reads as a crash. An orchestrator
(compose's ``stop_grace_period``, Kubernetes' ``terminationGracePeriodSeconds``) sends SIGTERM, waits,
then SIGKILLs; a service that is boring to operate uses that time like this:

1. **At once:** readiness (``/readyz``, ``/v2/health/ready``) answers 503 ``draining`` and new scoring
   requests get 503 ``not_ready`` with ``Retry-After`` (a client retries on another replica).
2. **Drain:** scoring requests already admitted -- in a pass or queued for one -- are answered, for at
   most ``drain_grace_s`` (shorter than the orchestrator's grace period, which the compose file sets);
   the socket stays open at least ``drain_notice_s``, so a balancer's probe sees the 503 even when idle.
3. **Stop:** uvicorn's normal shutdown (connections closed, the lifespan's shutdown), exit status 0.

A second SIGTERM, or SIGINT (Ctrl-C), stops at once as uvicorn always does.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import time
from types import FrameType

import uvicorn
from fastapi import FastAPI

__all__ = ["ServiceServer"]

log = logging.getLogger("service")

POLL_S = 0.02


class ServiceServer(uvicorn.Server):
    """uvicorn's server with the drain above on the first SIGTERM, and the reload on SIGHUP."""

    def __init__(self, config: uvicorn.Config, app: FastAPI, grace_s: float, notice_s: float = 0.0):
        super().__init__(config)
        self.app = app
        self.grace_s = grace_s
        self.notice_s = notice_s
        self.draining = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._drain_task: asyncio.Task | None = None

    async def serve(self, sockets=None) -> None:  # noqa: ANN001 - uvicorn's signature
        self._loop = asyncio.get_running_loop()
        self._loop.add_signal_handler(signal.SIGHUP, self._reload)
        try:
            await super().serve(sockets)
        finally:
            self._loop.remove_signal_handler(signal.SIGHUP)

    def _reload(self) -> None:
        log.info("SIGHUP: reloading the bundle at %s", self.app.state.settings.bundle_dir)
        asyncio.ensure_future(self.app.state.repository.reload())

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        if sig != signal.SIGTERM or self.draining or self._loop is None:
            super().handle_exit(sig, frame)
            return
        # not appended to uvicorn's captured signals: they would be re-raised after shutdown (status -15)
        self.draining = True
        self.begin_drain()
        self._loop.call_soon_threadsafe(self._start_drain)

    def begin_drain(self) -> None:
        """Readiness 503 and new work refused, from now on."""
        state = self.app.state
        if state.phase == "ready":
            state.phase = "draining"
        state.metrics.ready.set(0)

    def _start_drain(self) -> None:
        self._drain_task = asyncio.ensure_future(self._drain())

    def pending(self) -> tuple[int, int]:
        """(admitted scoring requests, plans queued for a pass)."""
        state = self.app.state
        batcher = getattr(state, "batcher", None)
        return state.in_flight.count, 0 if batcher is None else batcher.queued_plans

    async def _drain(self) -> None:
        start = time.monotonic()
        requests, plans = self.pending()
        log.info("SIGTERM: draining (%d requests in flight, %d plans queued; grace %.1f s)", requests, plans,
                 self.grace_s)
        while time.monotonic() - start < self.grace_s and (any(self.pending())
                                                           or time.monotonic() - start < self.notice_s):
            await asyncio.sleep(POLL_S)
        requests, plans = self.pending()
        if requests or plans:
            log.warning("drain: grace of %.1f s over with %d requests in flight, %d plans queued; stopping",
                        self.grace_s, requests, plans)
        else:
            log.info("drained in %.0f ms; stopping", (time.monotonic() - start) * 1000)
        self.should_exit = True
