"""Executing plans: timing contract, validation, and determinism within and across processes."""

import hashlib
import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from firp.core.contract import PlanValidationError
from planner_client.tamp import PlannerConfig, TampPlanner
from sim_worker.executor import execute_plan
from sim_worker.perception import observation
from sim_worker.tasks import sample_initial_blocks

SHORT_T = 48


@pytest.fixture(scope="module")
def planner():
    return TampPlanner(PlannerConfig(horizon=SHORT_T))


def _digest(result) -> str:
    return hashlib.sha256(result.frames.tobytes()).hexdigest()


def test_frames_states_and_label_are_recorded(small_world, planner):
    blocks = sample_initial_blocks("stacking", 1)
    plan = planner.plan("stacking", observation(blocks, 1, small_world.layout)).actions
    result = execute_plan(small_world, "stacking", blocks, plan)
    assert result.frames.shape == (SHORT_T, 32, 32, 3) and result.frames.dtype == np.uint8
    assert result.states.shape == (SHORT_T, small_world.state_size)
    assert isinstance(result.success, bool) and result.reason
    # frames[0] is the initial image: the blocks are where the sampler put them
    small_world.reset(blocks)
    np.testing.assert_array_equal(result.frames[0], small_world.render())
    assert result.sim_seconds == pytest.approx(SHORT_T / 4 + 1.5, abs=0.01)


def test_same_seed_and_plan_give_identical_frames_and_label(small_world, planner):
    blocks = sample_initial_blocks("replacement", 5)
    plan = planner.plan("replacement", observation(blocks, 5, small_world.layout)).actions
    a = execute_plan(small_world, "replacement", blocks, plan)
    b = execute_plan(small_world, "replacement", blocks, plan)
    assert _digest(a) == _digest(b)
    assert a.success == b.success
    np.testing.assert_array_equal(a.final_block_poses, b.final_block_poses)


_CHILD = textwrap.dedent("""
    import hashlib, json, sys
    from planner_client.tamp import PlannerConfig, TampPlanner
    from sim_worker.executor import execute_plan
    from sim_worker.perception import observation
    from sim_worker.scene import RenderConfig
    from sim_worker.tasks import sample_initial_blocks
    from sim_worker.world import World
    world = World(render=RenderConfig(height=32, width=32))
    blocks = sample_initial_blocks("stacking", 7)
    plan = TampPlanner(PlannerConfig(horizon=%d)).plan("stacking", observation(blocks, 7, world.layout)).actions
    r = execute_plan(world, "stacking", blocks, plan)
    print(json.dumps({"frames": hashlib.sha256(r.frames.tobytes()).hexdigest(),
                      "plan": hashlib.sha256(plan.tobytes()).hexdigest(), "success": r.success}))
""" % SHORT_T)


@pytest.mark.slow
def test_determinism_across_processes():
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    outs = [json.loads(subprocess.run([sys.executable, "-c", _CHILD], capture_output=True, text=True, check=True,
                                      env=env, cwd=os.getcwd()).stdout.strip().splitlines()[-1]) for _ in range(2)]
    assert outs[0] == outs[1]


def test_invalid_plan_is_rejected_before_anything_runs(small_world, planner):
    blocks = sample_initial_blocks("stacking", 1)
    plan = planner.plan("stacking", observation(blocks, 1, small_world.layout)).actions.copy()
    plan[3, 7] = 9.0  # joint1 far outside its limit
    with pytest.raises(PlanValidationError) as err:
        execute_plan(small_world, "stacking", blocks, plan)
    assert err.value.rule == "joint_limits" and err.value.field == "plan[3][7]"


def test_a_simulation_that_blows_up_ends_unstable_with_the_rest_blanked(planner, tmp_path, monkeypatch):
    """Negative joint damping pumps energy into the arm: the physics diverges within the first step.
    The execution stops there, is labelled a failure of kind "unstable", and nothing after the break
    looks like a real frame or state (zeros, NaN) -- a dataset must not learn from them."""
    from sim_worker.scene import RenderConfig
    from sim_worker.world import World

    monkeypatch.chdir(tmp_path)  # MuJoCo writes its warnings to MUJOCO_LOG.TXT in the working directory
    blocks = sample_initial_blocks("stacking", 1)
    with World(render=RenderConfig(height=32, width=32)) as world:
        plan = planner.plan("stacking", observation(blocks, 1, world.layout)).actions
        world.model.dof_damping[:] = -50.0
        result = execute_plan(world, "stacking", blocks, plan)
    assert result.unstable and not result.success
    assert (result.kind, result.reason) == ("unstable", "simulation became unstable")
    broke = int(np.flatnonzero(np.isnan(result.states).any(axis=1))[0])  # the first step never reached
    assert 0 < broke < SHORT_T and np.isnan(result.states[broke:]).all()
    assert np.isfinite(result.states[:broke]).all()
    assert result.frames[:broke].any(axis=(1, 2, 3)).all() and not result.frames[broke:].any()
    assert result.warnings  # MuJoCo's own warning counters say why
