"""Shared fixtures: one small-image World per test session (compiling the scene takes ~0.3 s)."""

from __future__ import annotations

import pytest

from sim_worker.scene import RenderConfig
from sim_worker.world import World


@pytest.fixture(scope="session")
def small_world() -> World:
    world = World(render=RenderConfig(height=32, width=32))
    yield world
    world.close()
