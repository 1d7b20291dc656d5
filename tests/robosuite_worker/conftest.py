"""The robosuite world's tests run in its own environment (``make test-robosuite``: .venv-robosuite).

One world per test session: making a robosuite environment takes seconds, a reset milliseconds.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", os.environ.get("MUJOCO_GL", "egl"))

from firp.core.contract import make_plan  # noqa: E402


@pytest.fixture(scope="session")
def world():
    from robosuite_worker.world import RobosuiteWorld

    w = RobosuiteWorld(image_size=64)
    yield w
    w.close()


def still_plan(joints: np.ndarray, t: int, fingers: float | None = None) -> np.ndarray:
    """A contract plan that holds the robot where it is (fingers as given, else as they are)."""
    targets = np.tile(joints, (t, 1))
    if fingers is not None:
        targets[:, 7:] = fingers
    return make_plan(np.zeros(t, dtype=int), targets)
