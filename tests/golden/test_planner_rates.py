"""The committed planner success rates (``docs/results/planner_rates.json``), seed by seed.

For a sample of each task's seeds, under both pose-error settings, every block order the benchmark
tried is planned and executed again: the success flag and the outcome's kind must be the recorded
ones. Executing held instead of interpolated joint targets, another block friction, another release
height or another perception error changes some of these outcomes.
"""

from __future__ import annotations

import pytest

from planner_client.tamp import TampPlanner
from sim_worker.executor import ExecutorConfig, execute_plan
from sim_worker.perception import PoseErrorConfig, observation
from sim_worker.tasks import reason_kind, sample_initial_blocks
from sim_worker.world import World

from .conftest import read_json

#: seeds per (task, error setting) replayed: the first ones of the committed per-seed records
SAMPLE = {"default": 12, "zero": 6}
RATES = read_json("planner_rates.json")


def _cases() -> list:
    cases = []
    for result in RATES["results"]:
        for row in result["per_seed"][: SAMPLE[result["error_setting"]]]:
            cases.append(pytest.param(result["task"], result["pose_error"], row,
                                      id=f"{result['task']}-{result['error_setting']}-seed{row['seed']}"))
    return cases


@pytest.fixture(scope="module")
def world_and_planner():
    with World() as world:
        yield world, TampPlanner()


@pytest.mark.parametrize("task, pose_error, row", _cases())
def test_every_tried_order_ends_as_recorded(world_and_planner, task, pose_error, row):
    world, planner = world_and_planner
    blocks = sample_initial_blocks(task, row["seed"], world.layout)
    obs = observation(blocks, row["seed"], world.layout, PoseErrorConfig(**pose_error))
    got, want = [], []
    for tried in row["tried"]:
        plan = planner.plan(task, obs, tuple(tried["order"])).actions
        result = execute_plan(world, task, blocks, plan, ExecutorConfig(record_frames=False))
        got.append((tuple(tried["order"]), result.success, result.kind))
        want.append((tuple(tried["order"]), tried["success"], reason_kind(tried["success"], tried["reason"])))
    assert got == want
