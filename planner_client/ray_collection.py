"""Collection on a Ray cluster: actors that each build their world once and simulate many episodes.

``firp collect --ray local|auto|ADDRESS`` runs the same episodes as the process pool
(:func:`planner_client.collect.run_collection`), on Ray instead:

* ``local`` starts a private single-node cluster with ``--workers`` CPUs for the run and stops it
  after; ``auto`` and an address join a cluster (:mod:`firp.core.ray_cluster`).
* Each actor runs the world's initializer once (its world, its planner) and then simulates episode
  after episode; it returns the finished :class:`~firp.core.episodes.EpisodeRecord` to the driver,
  which writes it as one atomic part file (a scene the planner cannot plan yields none). The cluster's nodes need no shared filesystem, only the
  same installed packages.
* An actor whose process dies is restarted by Ray and its unfinished calls are retried
  (``max_restarts`` / ``max_task_retries``); the driver writes each index once, so a killed worker
  costs a retry, never a lost or doubled episode. An episode is determined by its index alone, so the
  episodes are bit-identical to the process pool's.
"""

from __future__ import annotations

import os
from typing import Callable, Iterator

from firp.core.episodes import EpisodeRecord, write_episode_part
from firp.core.ray_cluster import IN_FLIGHT_PER_ACTOR, as_completed_on_actors, ray_session
from planner_client.collect import attempt_episode

__all__ = ["EpisodeSimulator", "IN_FLIGHT_PER_ACTOR", "simulate_on_ray"]


class EpisodeSimulator:
    """One Ray actor: a world and a planner, made once by ``initializer(*initargs)``."""

    def __init__(self, initializer: Callable, initargs: tuple, simulate_one: Callable[[int], EpisodeRecord]):
        os.environ.setdefault("MUJOCO_GL", "egl")
        initializer(*initargs)
        self._simulate_one = simulate_one

    def pid(self) -> int:
        return os.getpid()

    def simulate(self, index: int) -> tuple[int, EpisodeRecord | str]:
        """The episode's record, or why the planner could plan nothing for its scene."""
        return index, attempt_episode(self._simulate_one, index)


def simulate_on_ray(*, address: str, actors: int, pending: list[int], parts_dir, initializer: Callable,
                    initargs: tuple, simulate_one: Callable[[int], EpisodeRecord],
                    on_actors: Callable[[list], None] | None = None) -> Iterator[tuple[int, bool | None]]:
    """Simulate the ``pending`` episode indices on ``actors`` Ray actors; write each one's part file as it
    arrives and yield ``(index, success)`` (``success`` None: the scene was unplannable, nothing
    written). ``on_actors`` (tests, tools) receives the actor handles once they exist."""
    with ray_session(address, actors) as ray:
        remote = ray.remote(num_cpus=1, max_restarts=-1, max_task_retries=-1)(EpisodeSimulator)
        handles = [remote.remote(initializer, initargs, simulate_one)
                   for _ in range(max(1, min(actors, len(pending))))]
        if on_actors is not None:
            on_actors(handles)
        for index, record in as_completed_on_actors(ray, handles, pending, lambda actor, i: actor.simulate.remote(i)):
            if isinstance(record, str):  # unplannable scene: no episode
                yield index, None
                continue
            write_episode_part(parts_dir, index, record)
            yield index, bool(record.success)
