"""Trials of the main job on Ray actors: ``firp run --ray local|auto|ADDRESS --parallel K``.

Each of ``K`` actors builds our world in its own process once (:class:`~planner_client.embedded.EmbeddedSim`:
no sim worker to launch or address on the cluster's nodes) and keeps its own planner; every trial it is
given runs there end to end -- start the scene, plan, score on the run's scoring service over HTTP,
execute, the oracle line -- and only the trial's record travels back. The driver appends the records
to the run file in trial order, so the JSONL and ``--resume`` work as on one machine, and one scoring
service micro-batches every actor's calls.

An actor whose process dies is restarted by Ray and its trial run again (``max_restarts`` /
``max_task_retries``); a trial is determined by its seed, so the retried record equals the lost one but
for its timings and request id, and the driver writes each trial once.

What stays on one machine: recording executions (``--record`` writes part files on the driver's disk)
and robosuite's world (its own environment) -- both refused with ``--ray`` by the command line.
"""

from __future__ import annotations

import copy
import os
from dataclasses import dataclass
from typing import Any, Callable, Iterator

from firp.core.ray_cluster import as_completed_on_actors, ray_session

__all__ = ["RayTrials", "TrialRunner", "trials_on_ray"]


@dataclass(frozen=True)
class RayTrials:
    """Where and how wide: the cluster (``local``, ``auto`` or an address), the actors, and the scoring
    service every actor calls (None: ``--no-score``), which must be reachable from the cluster's nodes."""

    address: str
    actors: int
    service_url: str | None = None
    api_key: str | None = None


class TrialRunner:
    """One Ray actor: our world in this process, a planner, a client of the run's scoring service."""

    def __init__(self, config: Any, planner: Any, identity: dict, decision: Any, service_url: str | None,
                 api_key: str | None):
        os.environ.setdefault("MUJOCO_GL", "egl")
        from planner_client.clients import ScoreClient
        from planner_client.embedded import EmbeddedSim

        # a copy of its own: arrays that come out of Ray's object store are read-only, and the planner's IK
        # writes into its Jacobian buffers
        self.config, self.planner, self.identity, self.decision = config, copy.deepcopy(planner), identity, decision
        self.sim = EmbeddedSim()
        self.scorer = None if service_url is None else ScoreClient(service_url, api_key)

    def pid(self) -> int:
        return os.getpid()

    def run(self, trial: int) -> tuple[int, dict]:
        from planner_client.loop import run_trial

        return trial, run_trial(trial, self.config, self.sim, self.planner, self.scorer, self.identity,
                                decision=self.decision)


def trials_on_ray(spec: RayTrials, pending: list[int], *, config: Any, planner: Any, identity: dict,
                  decision: Any, on_actors: Callable[[list], None] | None = None) -> Iterator[dict]:
    """The ``pending`` trials' records, run on ``spec.actors`` actors and yielded in trial order.
    ``on_actors`` (tests, tools) receives the actor handles once they exist."""
    if not pending:
        return
    with ray_session(spec.address, spec.actors) as ray:
        remote = ray.remote(num_cpus=1, max_restarts=-1, max_task_retries=-1)(TrialRunner)
        planner_ref = ray.put(planner)  # held for the whole run: a restarted actor is built from it again
        handles = [remote.remote(config, planner_ref, identity, decision, spec.service_url, spec.api_key)
                   for _ in range(max(1, min(spec.actors, len(pending))))]
        if on_actors is not None:
            on_actors(handles)
        finished: dict[int, dict] = {}
        order = iter(pending)
        due = next(order)
        for trial, record in as_completed_on_actors(ray, handles, pending, lambda actor, t: actor.run.remote(t)):
            finished[trial] = record
            while due is not None and due in finished:
                yield finished.pop(due)
                due = next(order, None)
