"""The service's process: uvicorn's server with two signals of its own -- SIGTERM drains, SIGHUP reloads.

**SIGTERM** drains (:class:`firp.core.draining.DrainingServer`): readiness 503 ``draining`` at once,
new scoring requests 503 ``not_ready``, admitted requests -- in a pass or queued for one -- answered
within ``drain_grace_s``, then exit 0.

**SIGHUP** swaps in the configured bundle's directory, read again (:meth:`service.repository.
ModelRepository.reload`: load, verify, warm off the serving path, switch; a failure keeps the old
model and is logged).
"""

from __future__ import annotations

import asyncio
import logging
import signal

import uvicorn
from fastapi import FastAPI

from firp.core.draining import DrainingServer

__all__ = ["ServiceServer"]

log = logging.getLogger("service")


class ServiceServer(DrainingServer):
    """uvicorn's server for the scoring service app."""

    def __init__(self, config: uvicorn.Config, app: FastAPI, grace_s: float, notice_s: float = 0.0):
        super().__init__(config, begin_drain=self._begin_drain, pending=self._pending, grace_s=grace_s,
                         notice_s=notice_s, log=log)
        self.app = app

    def _begin_drain(self) -> None:
        state = self.app.state
        if state.phase == "ready":
            state.phase = "draining"
        state.metrics.ready.set(0)

    def _pending(self) -> int:
        """Admitted scoring requests (queued plans belong to admitted requests)."""
        return self.app.state.in_flight.count

    async def serve(self, sockets=None) -> None:  # noqa: ANN001 - uvicorn's signature
        loop = asyncio.get_running_loop()
        loop.add_signal_handler(signal.SIGHUP, self._reload)
        try:
            await super().serve(sockets)
        finally:
            loop.remove_signal_handler(signal.SIGHUP)

    def _reload(self) -> None:
        log.info("SIGHUP: reloading the bundle at %s", self.app.state.settings.bundle_dir)
        asyncio.ensure_future(self.app.state.repository.reload())
