"""An in-process simulator backend: what the planner client uses when no sim worker URL is given.

It offers the same two calls as the sim worker's HTTP API (start an episode and get the
observation; execute a plan from that episode's initial state), so the loop does not care which
one it talks to.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sim_worker.executor import ExecutorConfig, execute_plan
from sim_worker.perception import PoseErrorConfig, observation
from sim_worker.tasks import sample_initial_blocks
from sim_worker.world import World


@dataclass
class Episode:
    task: str
    seed: int
    observation: dict
    true_blocks: np.ndarray = field(repr=False)


@dataclass(frozen=True)
class Outcome:
    success: bool
    reason: str
    sim_seconds: float


class EmbeddedSim:
    """Runs the MuJoCo world in this process (no frames recorded: the loop only needs labels)."""

    def __init__(self, pose_error: PoseErrorConfig = PoseErrorConfig()):
        self.world = World()
        self.pose_error = pose_error

    def start(self, task: str, seed: int) -> Episode:
        blocks = sample_initial_blocks(task, seed, self.world.layout)
        return Episode(task, seed, observation(blocks, seed, self.world.layout, self.pose_error), blocks)

    def execute(self, episode: Episode, plan: np.ndarray) -> Outcome:
        r = execute_plan(self.world, episode.task, episode.true_blocks, plan, ExecutorConfig(record_frames=False))
        return Outcome(r.success, r.reason, r.sim_seconds)

    def close(self) -> None:
        self.world.close()
