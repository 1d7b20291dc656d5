"""Physics and rendering off the event loop, on one dedicated thread.

MuJoCo's ``MjData`` is not thread-safe, and an EGL/OSMesa context made current in one thread
cannot be made current in another while the first holds it, so a generic thread pool (which
hands each call to any free thread) is not enough: every world is built, stepped and rendered on
the same single thread. Requests queue behind each other there, which is also the right amount of
parallelism for a worker that owns one or two cores (run more worker processes to scale).
"""

from __future__ import annotations

import asyncio
import functools
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, TypeVar

import numpy as np

from sim_worker.executor import ExecutionResult
from sim_worker.imaging import encode_png_b64
from sim_worker.perception import PoseErrorConfig
from sim_worker.worlds import EpisodeStart, TaskWorlds

R = TypeVar("R")


@dataclass(frozen=True)
class Execution:
    result: ExecutionResult
    frames_b64: list[str] | None  # encoded on the sim thread too: it is CPU work per step


class SimRunner:
    """Async front of a :class:`TaskWorlds` that lives on its own thread."""

    def __init__(self, image_size: int):
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mujoco")
        self._worlds = TaskWorlds(image_size)

    async def _call(self, fn: Callable[..., R], *args: object) -> R:
        return await asyncio.get_running_loop().run_in_executor(self._pool, functools.partial(fn, *args))

    async def warm_up(self) -> None:
        await self._call(self._worlds.warm_up)

    async def begin(self, task: str, seed: int, pose_error: PoseErrorConfig) -> tuple[EpisodeStart, str]:
        """The episode's initial state and its image as base64 PNG."""
        def run() -> tuple[EpisodeStart, str]:
            start = self._worlds.begin(task, seed, pose_error)
            return start, encode_png_b64(start.image)
        return await self._call(run)

    async def execute(self, start: EpisodeStart, plan: np.ndarray, record_frames: bool) -> Execution:
        def run() -> Execution:
            result = self._worlds.execute(start.task, start.true_blocks, plan, record_frames)
            frames = [encode_png_b64(f) for f in result.frames] if result.frames is not None else None
            return Execution(result, frames)
        return await self._call(run)

    async def close(self) -> None:
        """Free the GL contexts on the thread that owns them, then stop the thread."""
        try:
            await self._call(self._worlds.close)
        finally:
            self._pool.shutdown(wait=True)
