"""StackThree's success check, on hand-placed cubes; the other tasks are robosuite's own environments."""

from __future__ import annotations

import numpy as np
import pytest

from robosuite_worker.tasks import TASKS


def _place(world, positions: dict[str, tuple[float, float, float]], settle_steps: int = 40) -> bool:
    env = world.env("stack_three")
    world._reset("stack_three", 0)
    top = env.table_offset[2]
    for cube in env.cubes:
        x, y, z = positions[cube.name]
        env.sim.data.set_joint_qpos(cube.joints[0], np.array([x, y, top + z, 1.0, 0.0, 0.0, 0.0]))
    env.sim.forward()
    hold = np.concatenate([world.joint_positions(env)[:7], [-1.0]])
    for _ in range(settle_steps):
        env.step(hold)
    return env._check_success()


def test_a_tower_of_three_in_any_order_succeeds(world):
    assert _place(world, {"cubeB": (0.0, 0.0, 0.025), "cubeA": (0.0, 0.0, 0.071), "cubeC": (0.0, 0.0, 0.112)})
    assert _place(world, {"cubeA": (0.0, 0.0, 0.02), "cubeC": (0.0, 0.0, 0.061), "cubeB": (0.0, 0.0, 0.108)})


@pytest.mark.parametrize("positions", [
    {"cubeA": (0.0, 0.0, 0.02), "cubeB": (0.1, 0.0, 0.025), "cubeC": (0.0, 0.1, 0.02)},  # three on the table
    {"cubeB": (0.0, 0.0, 0.025), "cubeA": (0.0, 0.0, 0.071), "cubeC": (0.0, 0.12, 0.02)},  # a tower of two
    {"cubeB": (0.0, 0.0, 0.025), "cubeA": (0.1, 0.0, 0.02), "cubeC": (0.0, 0.0, 0.071)},  # two and one
])
def test_anything_short_of_a_tower_of_three_fails(world, positions):
    assert not _place(world, positions)


def test_the_other_tasks_are_robosuites_environments():
    import robosuite

    import robosuite_worker.envs  # noqa: F401

    assert {TASKS["nut_assembly"].env, TASKS["nut_assembly_round"].env, TASKS["pick_place"].env} <= set(
        robosuite.ALL_ENVIRONMENTS)
    assert "StackThree" in robosuite.ALL_ENVIRONMENTS and TASKS["stack_three"].env == "StackThree"
    assert [t.horizon for t in TASKS.values()] == [80, 100, 100, 200]
