"""The robosuite worker's HTTP API: :class:`~robosuite_worker.world.RobosuiteWorld` behind :mod:`world_api`."""

from __future__ import annotations

import time
from typing import Callable

from fastapi import FastAPI

from robosuite_worker.settings import RobosuiteSettings
from robosuite_worker.world import RobosuiteWorld
from world_api import create_world_app

__all__ = ["create_app"]


def create_app(settings: RobosuiteSettings | None = None, clock: Callable[[], float] = time.time) -> FastAPI:
    settings = settings or RobosuiteSettings()
    world = RobosuiteWorld(settings.image_size, settings.camera, tasks=settings.tasks or None)
    return create_world_app(world, settings, clock,
                            title="firp robosuite worker")
