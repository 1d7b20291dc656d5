"""One World per task, framed by that task's camera: how an episode begins and how a plan runs.

The camera pose is compiled into the MuJoCo model, so a task's images can only come from a world
built with ``RenderConfig.for_task(task)`` -- exactly as ``collect`` builds its worlds, which is
what makes an episode's initial image identical to a dataset's ``frames[0]`` for the same task
and seed. The physics does not depend on the camera, so labels agree too.

Both the HTTP worker and the planner's embedded simulator start episodes here, so the two backends
cannot drift apart. Not thread-safe (MuJoCo data and GL contexts are not): call it from one thread.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sim_worker.executor import ExecutionResult, ExecutorConfig, execute_plan
from sim_worker.perception import PoseErrorConfig, observation
from sim_worker.scene import RenderConfig, SceneLayout
from sim_worker.tasks import TASK_NAMES, check_task, sample_initial_blocks
from sim_worker.world import World


@dataclass(frozen=True)
class EpisodeStart:
    """Everything an episode is, fixed by (task, seed, pose error): executions restart from it."""

    task: str
    seed: int
    true_blocks: np.ndarray = field(repr=False)  # (n, 4) x, y, z, yaw: the real initial state
    observation: dict = field(repr=False)  # what the planner is told (noisy estimates + layout)
    image: np.ndarray = field(repr=False)  # (H, W, 3) uint8 camera image of the initial state
    joint_positions: np.ndarray = field(repr=False)  # (9,) the robot's initial contract joints


class TaskWorlds:
    """Lazily built worlds, one per task, sharing one layout and image size."""

    def __init__(self, image_size: int = 84, layout: SceneLayout = SceneLayout()):
        self.image_size = image_size
        self.layout = layout
        self._worlds: dict[str, World] = {}

    def world(self, task: str) -> World:
        check_task(task)
        if task not in self._worlds:
            render = RenderConfig.for_task(task, self.image_size, self.image_size)
            self._worlds[task] = World(self.layout, render)
        return self._worlds[task]

    def warm_up(self) -> None:
        """Build every task's world and render once, so the first request pays no start-up cost
        (and a broken GL setup shows at start, not at the first episode)."""
        for task in TASK_NAMES:
            self.world(task).render()

    def begin(self, task: str, seed: int, pose_error: PoseErrorConfig = PoseErrorConfig()) -> EpisodeStart:
        """The seeded initial state, the planner's observation of it, and its camera image."""
        world = self.world(task)
        blocks = sample_initial_blocks(task, seed, self.layout)
        obs = observation(blocks, seed, self.layout, pose_error)
        world.reset(blocks)
        return EpisodeStart(task, seed, blocks, obs, world.render(), world.joint_positions())

    def execute(self, task: str, true_blocks: np.ndarray, plan: np.ndarray,
                record_frames: bool = False) -> ExecutionResult:
        """Run ``plan`` from the initial state ``true_blocks`` (the executor resets the world first)."""
        return execute_plan(self.world(task), task, true_blocks, plan, ExecutorConfig(record_frames=record_frames))

    def close(self) -> None:
        for world in self._worlds.values():
            world.close()
        self._worlds.clear()
