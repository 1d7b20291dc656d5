"""Our MuJoCo world as a :class:`world_api.WorldBackend`: the tasks, the seeded start, the execution."""

from __future__ import annotations

import math

import numpy as np

from sim_worker.perception import PoseErrorConfig
from sim_worker.scene import BLOCK_NAMES
from sim_worker.tasks import OUTCOME_KINDS, TASK_NAMES
from sim_worker.worlds import TaskWorlds
from world_api.backend import EpisodeStart, Outcome

__all__ = ["MujocoWorld", "block_poses_json"]


def _finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def block_poses_json(poses: np.ndarray) -> dict:
    """Block poses by name; a coordinate the physics lost (non-finite after a divergence) is null,
    since JSON has no NaN."""
    return {name: {"position": [_finite_or_none(v) for v in poses[i, :3]], "yaw": _finite_or_none(poses[i, 3])}
            for i, name in enumerate(BLOCK_NAMES)}


class MujocoWorld:
    """:class:`TaskWorlds` behind the API (its worlds are built lazily, on the runner's thread)."""

    name = "sim_worker"
    tasks = TASK_NAMES
    outcome_kinds = tuple(OUTCOME_KINDS)

    def __init__(self, image_size: int = 84):
        self.image_size = image_size
        self.worlds = TaskWorlds(image_size)

    def warm_up(self) -> None:
        self.worlds.warm_up()

    def begin(self, task: str, seed: int, pose_error_mm: float, pose_error_deg: float) -> EpisodeStart:
        start = self.worlds.begin(task, seed, PoseErrorConfig.from_mm_deg(pose_error_mm, pose_error_deg))
        return EpisodeStart(task, seed, start.observation, start.image, start.joint_positions, start.true_blocks)

    def execute(self, start: EpisodeStart, plan: np.ndarray, record_frames: bool) -> Outcome:
        r = self.worlds.execute(start.task, start.state, plan, record_frames)
        return Outcome(bool(r.success), r.kind, r.reason, block_poses_json(r.final_block_poses), r.sim_seconds,
                       bool(r.unstable), r.frames)

    def close(self) -> None:
        self.worlds.close()
