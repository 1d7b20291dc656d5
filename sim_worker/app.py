"""The sim worker's HTTP API: our MuJoCo world behind the API every world serves (:mod:`world_api`)."""

from __future__ import annotations

import time
from typing import Callable

from fastapi import FastAPI

from sim_worker.backend import MujocoWorld
from sim_worker.settings import SimWorkerSettings
from world_api import create_world_app

__all__ = ["create_app"]


def create_app(settings: SimWorkerSettings | None = None, clock: Callable[[], float] = time.time) -> FastAPI:
    """The app; ``clock`` (seconds since the epoch) is injectable so tests can expire episodes."""
    settings = settings or SimWorkerSettings()
    return create_world_app(MujocoWorld(settings.image_size), settings, clock, title="firp sim worker")
