"""``python -m robosuite_worker serve`` as an operator starts it, and the planner's own client against it."""

from __future__ import annotations

import numpy as np

from firp.core.contract import make_plan
from planner_client.clients import SimClient
from tests.processes import ServedProcess, clean_env


def test_the_worker_serves_the_planners_sim_client_unchanged():
    env = clean_env("FIRP_ROBOSUITE_", FIRP_ROBOSUITE_IMAGE_SIZE="48")
    with ServedProcess("robosuite_worker", ["serve", "--port", "0"], env) as worker:
        with SimClient(worker.base) as sim:
            sim.wait_ready(timeout=300)
            episode = sim.start("nut_assembly", 2)
            assert episode.image_size == (48, 48) and "SquareNut" in episode.observation["blocks"]
            joints = np.array(episode.robot["joint_positions"])
            outcome = sim.execute(episode, make_plan(np.zeros(8, dtype=int), np.tile(joints, (8, 1))))
            assert (outcome.success, outcome.kind, outcome.unstable) == (False, "not_done", False)
            again = sim.execute(episode, make_plan(np.zeros(8, dtype=int), np.tile(joints, (8, 1))))
            assert again.final_blocks == outcome.final_blocks
    assert worker.returncode == 0, worker.log
