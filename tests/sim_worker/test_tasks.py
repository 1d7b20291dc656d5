"""Success predicates on hand-placed physics states, and the initial-state sampler."""

import numpy as np
import pytest

from sim_worker.scene import SceneLayout
from sim_worker.tasks import TASK_NAMES, SamplerConfig, judge, sample_initial_blocks, square_gap

LAYOUT = SceneLayout()
H = LAYOUT.block_half


def settle(world, poses, seconds=1.0):
    """Place the blocks by hand, let physics run with the arm at home, return the verdict inputs."""
    import mujoco

    world.reset(np.asarray(poses, dtype=float))
    world.data.ctrl[:] = world.panda.ctrl_for(world.joint_positions())
    mujoco.mj_step(world.model, world.data, nstep=int(seconds / world.model.opt.timestep))
    return world.block_states()


def test_perfect_tower_succeeds(small_world):
    poses = [[0.5, 0.0, H, 0.1], [0.5, 0.0, 3 * H + 0.0005, 0.1], [0.5, 0.0, 5 * H + 0.001, 0.1]]
    verdict = judge("stacking", settle(small_world, poses))
    assert verdict.success, verdict.reason


def test_tower_in_any_colour_order_succeeds(small_world):
    poses = [[0.5, 0.0, 5 * H + 0.001, 0.0], [0.5, 0.0, H, 0.0], [0.5, 0.0, 3 * H + 0.0005, 0.0]]
    assert judge("stacking", settle(small_world, poses)).success


def test_toppled_tower_fails(small_world):
    # the top block overhangs by 65%: it falls off during settling
    poses = [[0.5, 0.0, H, 0.0], [0.5, 0.0, 3 * H + 0.0005, 0.0], [0.5 + 1.3 * H, 0.0, 5 * H + 0.001, 0.0]]
    verdict = judge("stacking", settle(small_world, poses))
    assert not verdict.success
    assert "height" in verdict.reason or "tilted" in verdict.reason or "off the block" in verdict.reason


def test_misaligned_but_standing_tower_fails(small_world):
    poses = [[0.5, 0.0, H, 0.0], [0.5, 0.0, 3 * H + 0.0005, 0.0], [0.5 + 0.9 * H, 0.0, 5 * H + 0.001, 0.0]]
    verdict = judge("stacking", settle(small_world, poses))
    assert not verdict.success and "off the block below" in verdict.reason


def test_blocks_side_by_side_are_not_a_tower(small_world):
    poses = [[0.45, 0.0, H, 0.0], [0.5, 0.0, H, 0.0], [0.55, 0.0, H, 0.0]]
    assert not judge("stacking", settle(small_world, poses)).success


def test_all_blocks_in_box_b_succeeds(small_world):
    box = LAYOUT.box("box_b")
    cx, cy = box.centre
    z = box.floor_top + H
    poses = [[cx - 0.05, cy - 0.04, z, 0.0], [cx + 0.05, cy - 0.04, z, 0.2], [cx, cy + 0.05, z, -0.3]]
    verdict = judge("replacement", settle(small_world, poses))
    assert verdict.success, verdict.reason


def test_block_outside_box_b_fails(small_world):
    box = LAYOUT.box("box_b")
    cx, cy = box.centre
    z = box.floor_top + H
    poses = [[cx - 0.05, cy - 0.04, z, 0.0], [cx + 0.05, cy - 0.04, z, 0.0], [0.5, 0.0, H, 0.0]]
    verdict = judge("replacement", settle(small_world, poses))
    assert not verdict.success and "green" not in verdict.reason and "blue" in verdict.reason


def test_block_left_in_box_a_fails(small_world):
    a, b = LAYOUT.box("box_a"), LAYOUT.box("box_b")
    z = b.floor_top + H
    poses = [[b.centre[0] - 0.05, b.centre[1], z, 0.0], [a.centre[0], a.centre[1], z, 0.0],
             [b.centre[0] + 0.05, b.centre[1], z, 0.0]]
    verdict = judge("replacement", settle(small_world, poses))
    assert not verdict.success and "green" in verdict.reason


def test_moving_block_is_not_at_rest(small_world):
    poses = [[0.5, 0.0, H, 0.0], [0.5, 0.0, 3 * H + 0.0005, 0.0], [0.5, 0.0, 5 * H + 0.001, 0.0]]
    settle(small_world, poses)
    small_world.data.qvel[small_world.blocks.qvel[2]] = 0.5
    verdict = judge("stacking", small_world.block_states())
    assert not verdict.success and "not at rest" in verdict.reason


@pytest.mark.parametrize("task", TASK_NAMES)
def test_sampler_is_seeded_and_keeps_blocks_apart(task):
    a = sample_initial_blocks(task, 123)
    b = sample_initial_blocks(task, 123)
    c = sample_initial_blocks(task, 124)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    gap = SamplerConfig().stack_min_gap if task == "stacking" else SamplerConfig().box_min_gap
    for seed in range(30):
        poses = sample_initial_blocks(task, seed)
        for i in range(3):
            for j in range(i + 1, 3):
                assert square_gap(poses[i, :2], poses[i, 3], poses[j, :2], poses[j, 3], H) >= gap - 1e-12
        if task == "replacement":
            box = LAYOUT.box("box_a")
            assert np.all(np.abs(poses[:, :2] - box.centre) <= np.asarray(box.inner_half) - H)


def test_square_gap_by_hand():
    # axis-aligned unit-half squares 3 apart along x: faces 1 apart
    assert square_gap(np.zeros(2), 0.0, np.array([3.0, 0.0]), 0.0, 1.0) == pytest.approx(1.0)
    # overlapping
    assert square_gap(np.zeros(2), 0.0, np.array([1.0, 0.0]), 0.0, 1.0) == pytest.approx(-1.0)
    # a 45-degree square reaches sqrt(2) along x
    assert square_gap(np.zeros(2), 0.0, np.array([3.0, 0.0]), np.pi / 4, 1.0) == pytest.approx(2 - np.sqrt(2))


def test_unknown_task_is_rejected():
    with pytest.raises(ValueError, match="task: unknown task 'juggling'"):
        sample_initial_blocks("juggling", 0)


def test_tied_heights_are_ordered_by_block_index_not_by_the_last_bits_of_the_physics():
    """Two blocks lying on the table are one level: which of them the verdict names (and, when one is
    tilted, which check fails first) must not depend on a height difference of a few nanometres."""
    from sim_worker.tasks import BlockState, judge, tower_order

    assert tower_order([0.02 + 1e-9, 0.02, 0.06], tie=0.002) == [0, 1, 2]
    assert tower_order([0.02, 0.02 + 1e-9, 0.06], tie=0.002) == [0, 1, 2]
    assert tower_order([0.10, 0.06, 0.02], tie=0.002) == [2, 1, 0]
    flat = lambda x, z, tilt=0.0: BlockState(np.array([x, 0.0, z]), tilt, 0.0)  # noqa: E731
    for eps in (0.0, 1e-9, -1e-9):
        # red and green on the table, green tilted; blue on top of red
        blocks = [flat(0.5, 0.02 + eps), flat(0.6, 0.02, tilt=20.0), flat(0.5, 0.06)]
        verdict = judge("stacking", blocks)
        assert (verdict.success, verdict.kind) == (False, "wrong_height")
        assert verdict.reason.startswith("green at height 0.020, expected 0.060")


def test_each_check_of_the_predicates_has_its_kind():
    from sim_worker.tasks import OUTCOME_KINDS, BlockState, Verdict, judge, reason_kind

    block = lambda x, y, z, tilt=0.0, speed=0.0: BlockState(np.array([x, y, z]), tilt, speed)  # noqa: E731
    tower = [block(0.5, 0.0, 0.02), block(0.5, 0.0, 0.06), block(0.5, 0.0, 0.10)]
    assert judge("stacking", tower).kind == "success"
    cases = {
        "not_at_rest": [block(0.5, 0.0, 0.02), block(0.5, 0.0, 0.06), block(0.5, 0.0, 0.10, speed=0.5)],
        "wrong_height": [block(0.5, 0.0, 0.02), block(0.7, 0.0, 0.02), block(0.5, 0.0, 0.06)],
        "tilted": [block(0.5, 0.0, 0.02), block(0.5, 0.0, 0.06, tilt=15.0), block(0.5, 0.0, 0.10)],
        "off_block_below": [block(0.5, 0.0, 0.02), block(0.52, 0.0, 0.06), block(0.52, 0.0, 0.10)],
    }
    for kind, blocks in cases.items():
        verdict = judge("stacking", blocks)
        assert (verdict.success, verdict.kind) == (False, kind), verdict
        assert reason_kind(False, verdict.reason) == kind  # records without kinds read back the same
    assert judge("replacement", tower).kind == "not_inside"
    assert set(OUTCOME_KINDS) == {"success", *cases, "not_inside", "unstable"}
    with pytest.raises(ValueError, match="contradicts"):
        Verdict(True, "x", "tilted")
    with pytest.raises(ValueError, match="matches no outcome kind"):
        reason_kind(False, "the arm fell off")
