"""A world off the event loop, on one dedicated thread.

Simulators' data is not thread-safe, and an EGL/OSMesa context made current in one thread cannot be
made current in another while the first holds it, so a generic thread pool (which hands each call
to any free thread) is not enough: every world is built, stepped and rendered on the same single
thread. Requests queue behind each other there, which is also the right amount of parallelism for a
worker that owns one or two cores (run more worker processes to scale).

The queue is bounded (``max_queued`` calls waiting or running; one more is refused with 503
``overloaded`` and ``Retry-After``), and a call whose deadline passed while it waited is dropped
before the world runs it (504 ``deadline_exceeded``): a simulation costs seconds, so work nobody
waits for any more is the most expensive kind.
"""

from __future__ import annotations

import asyncio
import functools
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, TypeVar

import numpy as np

from firp.core.deadlines import deadline_exceeded
from firp.core.http_errors import ApiError
from firp.core.tracing import record_span
from world_api.backend import EpisodeStart, Outcome, WorldBackend
from world_api.images import encode_png_b64

if TYPE_CHECKING:
    from opentelemetry.trace import Tracer

R = TypeVar("R")


@dataclass(frozen=True)
class Execution:
    outcome: Outcome
    frames_b64: list[str] | None  # encoded on the world's thread too: it is CPU work per step


class WorldRunner:
    """Async front of a :class:`WorldBackend` that lives on its own thread."""

    def __init__(self, backend: WorldBackend, max_queued: int | None = None, retry_after_s: int = 1,
                 tracer: Tracer | None = None):
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="world")
        self.backend = backend
        self.max_queued = max_queued
        self.retry_after_s = retry_after_s
        self.pending = 0  # bounded calls waiting for the world's thread or running on it
        self.tracer = tracer  # None: tracing off (firp.core.tracing)

    async def _call(self, fn: Callable[..., R], *args: object) -> R:
        return await asyncio.get_running_loop().run_in_executor(self._pool, functools.partial(fn, *args))

    async def _bounded(self, fn: Callable[[], R], deadline: float | None, span: str) -> R:
        """``fn`` on the world's thread, if the queue has room and its deadline has not passed when its
        turn comes; traced as ``world queue wait`` then ``span`` when tracing is on."""
        if self.max_queued is not None and self.pending >= self.max_queued:
            raise ApiError(503, None, "overloaded", f"{self.pending} calls are waiting for this world, the most it "
                           "queues (setting max_queued); retry later, or on another worker",
                           headers={"Retry-After": str(self.retry_after_s)})
        budget = None if deadline is None else deadline - time.monotonic()
        times = [time.time_ns()]  # queued, then started and ended on the world's thread

        def guarded() -> R | None:
            times.append(time.time_ns())
            if deadline is not None and time.monotonic() >= deadline:
                return None  # dropped: never run
            try:
                return fn()
            finally:
                times.append(time.time_ns())

        self.pending += 1
        try:
            result = await self._call(guarded)
        finally:
            self.pending -= 1
            self._trace(span, times)
        if result is None:
            raise deadline_exceeded("queued", budget)
        return result

    def _trace(self, span: str, times: list[int]) -> None:
        """The call's spans in the request's trace, from the times its thread recorded."""
        if self.tracer is None:
            return
        dropped = len(times) == 2
        record_span(self.tracer, "world queue wait", times[0], times[1] if len(times) > 1 else time.time_ns(),
                    error="deadline_exceeded" if dropped else None)
        if len(times) == 3:
            record_span(self.tracer, span, times[1], times[2], {"firp.world": self.backend.name})

    async def warm_up(self) -> None:
        await self._call(self.backend.warm_up)

    async def begin(self, task: str, seed: int, pose_error_mm: float, pose_error_deg: float,
                    deadline: float | None = None) -> tuple[EpisodeStart, str]:
        """The episode's initial state and its image as base64 PNG."""
        def run() -> tuple[EpisodeStart, str]:
            start = self.backend.begin(task, seed, pose_error_mm, pose_error_deg)
            return start, encode_png_b64(start.image)
        return await self._bounded(run, deadline, "begin episode")

    async def execute(self, start: EpisodeStart, plan: np.ndarray, record_frames: bool,
                      deadline: float | None = None) -> Execution:
        def run() -> Execution:
            outcome = self.backend.execute(start, plan, record_frames)
            frames = [encode_png_b64(f) for f in outcome.frames] if outcome.frames is not None else None
            return Execution(outcome, frames)
        return await self._bounded(run, deadline, "execute")

    async def close(self) -> None:
        """Free the world (its GL contexts) on the thread that owns it, then stop the thread."""
        try:
            await self._call(self.backend.close)
        finally:
            self._pool.shutdown(wait=True)
