"""What a world must offer the API: its tasks, a seeded episode start, a plan's execution."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np


@dataclass(frozen=True)
class EpisodeStart:
    """Everything an episode is, fixed by (task, seed, pose error): every execution restarts from it."""

    task: str
    seed: int
    observation: dict  # what the planner is told: {"blocks": {name: {position, yaw}}, "scene": {...}}
    image: np.ndarray = field(repr=False)  # (H, W, 3) uint8, the camera image of the initial state
    joint_positions: np.ndarray = field(repr=False)  # (9,) the robot's initial contract joints
    state: Any = field(default=None, repr=False)  # the world's own record of the initial state


@dataclass(frozen=True)
class Outcome:
    """A plan's execution, as the API reports it."""

    success: bool
    kind: str  # "success", or the world's name of what failed
    reason: str  # for people
    final_blocks: dict  # name -> {"position": [x, y, z] (None where the physics lost it), "yaw"}
    sim_seconds: float
    unstable: bool
    frames: np.ndarray | None = field(default=None, repr=False)  # (T, H, W, 3) uint8, frame t before step t
    states: np.ndarray | None = field(default=None, repr=False)  # (T, S) the world's state before step t (with frames)


class WorldBackend(Protocol):
    """A world behind the API. Its methods are only ever called from the runner's one thread."""

    name: str
    tasks: tuple[str, ...]
    outcome_kinds: tuple[str, ...]
    image_size: int

    def warm_up(self) -> None: ...

    def begin(self, task: str, seed: int, pose_error_mm: float, pose_error_deg: float) -> EpisodeStart: ...

    def execute(self, start: EpisodeStart, plan: np.ndarray, record_frames: bool) -> Outcome: ...

    def close(self) -> None: ...
