"""An in-process simulator backend: what the planner client uses when no sim worker URL is given.

It offers the same two calls as the sim worker's HTTP API (start an episode and get the
observation and initial image; execute a plan from that episode's initial state), both satisfying
:class:`planner_client.backend.SimBackend`, so the loop does not care which one it talks to. Both
start episodes through ``sim_worker.worlds.TaskWorlds``, so they give identical episodes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from world_api.images import encode_png_b64
from sim_worker.perception import PoseErrorConfig
from sim_worker.worlds import TaskWorlds


@dataclass
class Episode:
    task: str
    seed: int
    observation: dict
    true_blocks: np.ndarray = field(repr=False)
    image_b64: str = field(default="", repr=False)


@dataclass(frozen=True)
class Outcome:
    success: bool
    reason: str
    sim_seconds: float
    kind: str
    frames: np.ndarray | None = field(default=None, repr=False)  # (T, H, W, 3), only when asked for


class EmbeddedSim:
    """Runs the MuJoCo worlds in this process (frames only when asked: the loop needs labels, a
    recording run (``--record``) the frames too)."""

    def __init__(self, pose_error: PoseErrorConfig = PoseErrorConfig(), image_size: int = 84):
        self.worlds = TaskWorlds(image_size)
        self.pose_error = pose_error

    def start(self, task: str, seed: int) -> Episode:
        start = self.worlds.begin(task, seed, self.pose_error)
        return Episode(task, seed, start.observation, start.true_blocks, encode_png_b64(start.image))

    def execute(self, episode: Episode, plan: np.ndarray, record_frames: bool = False) -> Outcome:
        r = self.worlds.execute(episode.task, episode.true_blocks, plan, record_frames=record_frames)
        return Outcome(r.success, r.reason, r.sim_seconds, r.kind, r.frames if record_frames else None)

    def close(self) -> None:
        self.worlds.close()
