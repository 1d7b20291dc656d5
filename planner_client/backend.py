"""What the trial loop needs of a simulator, whichever one runs it.

Two backends satisfy this: :class:`planner_client.embedded.EmbeddedSim` (MuJoCo in this process)
and :class:`planner_client.clients.SimClient` (the sim worker over HTTP). The loop is written
against these protocols only, so choosing a backend is a command-line decision, not a code change.
"""

from __future__ import annotations

from typing import Protocol, TypeVar, runtime_checkable

import numpy as np


class SimEpisode(Protocol):
    """A started episode: what the planner is told and what the scorer sees."""

    @property
    def task(self) -> str: ...

    @property
    def seed(self) -> int: ...

    @property
    def observation(self) -> dict: ...  # sim_worker.perception.observation's dict

    @property
    def image_b64(self) -> str: ...  # initial camera image, base64 PNG (the dataset's frame 0)


class SimOutcome(Protocol):
    """The label of one execution."""

    @property
    def success(self) -> bool: ...

    @property
    def reason(self) -> str: ...  # for people

    @property
    def kind(self) -> str: ...  # for programs: "success" or the world's name of the failed check

    @property
    def sim_seconds(self) -> float: ...


E = TypeVar("E", bound=SimEpisode)


@runtime_checkable
class SimBackend(Protocol[E]):
    """Start seeded episodes and execute plans on them, always from the episode's initial state."""

    def start(self, task: str, seed: int) -> E: ...

    def execute(self, episode: E, plan: np.ndarray, record_frames: bool = False) -> SimOutcome: ...

    def close(self) -> None: ...
