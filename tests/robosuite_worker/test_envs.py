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


def test_stack_three_has_a_close_camera_looking_at_the_cubes(world):
    """``workspaceview`` looks at the point it was aimed at, upright, and a cube fills more of it than of agentview."""
    from robosuite_worker.envs.stack_three import WORKSPACE_CAMERA
    from robosuite_worker.world import RobosuiteWorld

    env = world.env("stack_three")
    world._reset("stack_three", 0)
    position, target, fovy = WORKSPACE_CAMERA
    camera = env.sim.model.camera_name2id("workspaceview")
    axes = np.asarray(env.sim.data.cam_xmat[camera]).reshape(3, 3)
    looking = np.asarray(target) - np.asarray(position)
    np.testing.assert_allclose(-axes[:, 2], looking / np.linalg.norm(looking), atol=1e-6)
    assert axes[2, 1] > 0 and abs(axes[2, 0]) < 1e-6  # the image's up is the world's up; no roll
    assert env.sim.model.cam_fovy[camera] == pytest.approx(fovy)

    def cube_pixels(camera_name: str) -> int:
        # the red cube alone: robosuite's red wood texture, far from the table's white and the arm's grey
        close = RobosuiteWorld(image_size=84, camera=camera_name)
        try:
            image = close.render(close._reset("stack_three", 0)).astype(int)
        finally:
            close.close()
        red = (image[..., 0] > 90) & (image[..., 0] > image[..., 1] + 40) & (image[..., 0] > image[..., 2] + 40)
        return int(red.sum())

    assert cube_pixels("workspaceview") > 3 * cube_pixels("agentview") > 0


def test_a_camera_the_task_lacks_is_named_with_the_ones_it_has():
    from robosuite_worker.world import RobosuiteWorld

    world = RobosuiteWorld(camera="workspaceview")
    try:
        with pytest.raises(ValueError, match="'workspaceview' is not a camera of the nut_assembly task; one of .*agentview"):
            world.env("nut_assembly")
        assert "nut_assembly" not in world._envs  # the refused environment is closed, not kept
    finally:
        world.close()
