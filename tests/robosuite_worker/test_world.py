"""The robosuite world: seeded episodes, perception, plans under absolute joint control, outcomes."""

from __future__ import annotations

import numpy as np
import pytest

from robosuite_worker.tasks import TASKS
from robosuite_worker.world import STEPS_PER_PLAN_STEP, gripper_action

from .conftest import still_plan


@pytest.mark.parametrize("task", sorted(TASKS))
def test_an_episode_is_its_seed_and_a_plan_runs_from_its_initial_state(world, task):
    a, b, other = world.begin(task, 7, 3.0, 3.0), world.begin(task, 7, 3.0, 3.0), world.begin(task, 8, 3.0, 3.0)
    assert a.observation == b.observation and np.array_equal(a.image, b.image)
    assert a.observation["blocks"] != other.observation["blocks"] and not np.array_equal(a.image, other.image)
    assert a.image.shape == (64, 64, 3) and a.image.dtype == np.uint8 and a.joint_positions.shape == (9,)
    plan = still_plan(a.joint_positions, 8)
    first, again = world.execute(a, plan, record_frames=True), world.execute(a, plan, record_frames=False)
    # holding still changes nothing: not done, and the same outcome every time from the initial state
    assert (first.success, first.kind, first.unstable) == (False, "not_done", False)
    assert first.reason.startswith(TASKS[task].env) and first.final_blocks == again.final_blocks
    assert first.frames.shape == (8, 64, 64, 3) and np.array_equal(first.frames[0], a.image)
    # simulated time: the initial settling second, the plan's 8 steps at 4 FPS, the final settling second
    assert first.sim_seconds == pytest.approx(1.0 + 8 / 4 + 1.0, abs=0.06)
    assert set(first.final_blocks) == set(a.observation["blocks"])


def test_perception_is_seeded_and_has_the_asked_size(world):
    exact = world.begin("stack_three", 3, 0.0, 0.0)
    noisy = world.begin("stack_three", 3, 5.0, 5.0)
    again = world.begin("stack_three", 3, 5.0, 5.0)
    assert noisy.observation == again.observation
    env = world.env("stack_three")
    truth = {c.name: env.sim.data.body_xpos[b] for c, b in zip(env.cubes, env.cube_body_ids)}
    for name, pose in exact.observation["blocks"].items():
        np.testing.assert_allclose(pose["position"], truth[name], atol=1e-9)
    offsets = [np.linalg.norm(np.subtract(noisy.observation["blocks"][n]["position"][:2], truth[n][:2]))
               for n in truth]
    assert 0 < max(offsets) < 0.03  # a few mm, not cm
    assert exact.observation["scene"]["cube_half"] == {"cubeA": 0.02, "cubeB": 0.025, "cubeC": 0.02}


def test_the_plans_joint_targets_are_what_the_arm_reaches(world):
    """Absolute joint-position control: a plan that moves one joint by 0.3 rad ends there."""
    start = world.begin("stack_three", 1, 0.0, 0.0)
    goal = start.joint_positions.copy()
    goal[0] += 0.3
    plan = still_plan(start.joint_positions, 12)
    plan[4:, 7:] = goal  # from step 4 on, the new target
    world.execute(start, plan, record_frames=False)
    reached = world.joint_positions(world.env("stack_three"))
    assert abs(reached[0] - goal[0]) < 0.02 and np.abs(reached[1:7] - goal[1:7]).max() < 0.02
    assert STEPS_PER_PLAN_STEP == 5  # 20 Hz control, 4 FPS plans


def test_the_finger_targets_open_and_close_robosuites_gripper(world):
    assert gripper_action(np.array([0.04, 0.04])) == -1.0 and gripper_action(np.array([0.0, 0.0])) == 1.0
    assert gripper_action(np.array([0.025, 0.025])) == -1.0 and gripper_action(np.array([0.015, 0.015])) == 1.0
    start = world.begin("stack_three", 2, 0.0, 0.0)
    world.execute(start, still_plan(start.joint_positions, 8, fingers=0.0), record_frames=False)
    closed = world.joint_positions(world.env("stack_three"))[7:]
    world.execute(start, still_plan(start.joint_positions, 8, fingers=0.04), record_frames=False)
    opened = world.joint_positions(world.env("stack_three"))[7:]
    assert closed.max() < 0.005 and opened.min() > 0.035


def test_an_unknown_task_is_named():
    from robosuite_worker.tasks import check_task

    with pytest.raises(ValueError, match="task: unknown task 'juggling'"):
        check_task("juggling")


def test_a_shift_moves_and_turns_the_named_object_of_the_scene_at_rest(world):
    start = world.begin("stack_three", 5, 0.0, 0.0)
    plan = still_plan(start.joint_positions, 8)
    still = world.execute(start, plan, record_frames=False)
    moved = world.execute(start, plan, record_frames=False, shift={"cubeA": (0.01, -0.005, np.radians(10.0))})
    a0, a1 = np.asarray(still.final_blocks["cubeA"]["position"]), np.asarray(moved.final_blocks["cubeA"]["position"])
    np.testing.assert_allclose(a1[:2] - a0[:2], [0.01, -0.005], atol=1e-3)  # resting where it was put
    turned = np.angle(np.exp(1j * (moved.final_blocks["cubeA"]["yaw"] - still.final_blocks["cubeA"]["yaw"])))
    assert abs(np.degrees(turned) - 10.0) < 1.0
    np.testing.assert_allclose(moved.final_blocks["cubeB"]["position"], still.final_blocks["cubeB"]["position"],
                               atol=1e-4)  # the others stay
    with pytest.raises(ValueError, match="not an object of this task"):
        world.execute(start, plan, record_frames=False, shift={"SquareNut": (0.0, 0.0, 0.0)})


def test_closing_one_world_leaves_another_worlds_frames_intact():
    """robosuite frees a render context in whichever GL context is current; the world frees each in its own."""
    from robosuite_worker.world import RobosuiteWorld

    kept, closed = RobosuiteWorld(image_size=32), RobosuiteWorld(image_size=32)
    try:
        closed.begin("stack_three", 0, 3.0, 3.0)
        before = kept.begin("stack_three", 7, 3.0, 3.0).image  # kept's GL context is now the current one
        closed.close()
        assert np.array_equal(kept.begin("stack_three", 7, 3.0, 3.0).image, before)
    finally:
        kept.close()
        closed.close()
