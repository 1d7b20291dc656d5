"""The TAMP-style planner: contract-valid plans, natural category order, IK reaching its targets."""

import itertools

import numpy as np
import pytest

from firp.core.contract import CATEGORIES, PICK_PLACE_SEQUENCE, split_plan, validate_plan
from planner_client.ik import IKFailure, PandaIK
from planner_client.tamp import TampPlanner, block_orders
from sim_worker.perception import PoseErrorConfig, observation
from sim_worker.scene import SceneLayout
from sim_worker.tasks import sample_initial_blocks

LAYOUT = SceneLayout()


@pytest.fixture(scope="module")
def planner():
    return TampPlanner()


def _runs(categories: np.ndarray) -> list[str]:
    return [CATEGORIES[k] for k, _ in itertools.groupby(categories.tolist())]


@pytest.mark.parametrize("task,moved", [("stacking", 2), ("replacement", 3)])
def test_plan_is_valid_and_follows_the_natural_category_order(planner, task, moved):
    blocks = sample_initial_blocks(task, 3)
    plan = planner.plan(task, observation(blocks, 3, LAYOUT))
    actions = validate_plan(plan.actions)
    assert actions.shape == (120, 16)
    categories, targets = split_plan(actions)
    assert _runs(categories) == list(PICK_PLACE_SEQUENCE) * moved
    assert len(plan.grasp_yaws) == moved


def test_grasp_step_puts_the_tcp_on_the_estimated_block(planner):
    blocks = sample_initial_blocks("stacking", 4)
    obs = observation(blocks, 4, LAYOUT)
    plan = planner.plan("stacking", obs, ("red", "green", "blue"))
    categories, targets = split_plan(plan.actions)
    first_grasp = int(np.flatnonzero(categories == CATEGORIES.index("grasp"))[0])
    pos, _ = planner.ik.forward(targets[first_grasp, :7])
    np.testing.assert_allclose(pos, obs["blocks"]["green"]["position"], atol=1e-3)
    # the fingers close during the grasp and open at release
    assert targets[first_grasp - 1, 7] == pytest.approx(0.04)
    release = np.flatnonzero(categories == CATEGORIES.index("release"))
    release = release[: int(np.argmax(np.diff(release) > 1)) + 1]  # the first release run
    assert np.all(np.diff(targets[release, 7]) > 0)  # opening during the first release
    assert targets[release[-1] + 1, 7] == pytest.approx(0.04)  # open when moving away


def test_stacking_places_on_the_estimated_base(planner):
    """Each moved block is released 5 mm above its resting height on the estimated base (4 cm blocks),
    and the plan's joint targets really put the TCP there (forward kinematics of the release steps)."""
    blocks = sample_initial_blocks("stacking", 2)
    obs = observation(blocks, 2, LAYOUT)
    plan = planner.plan("stacking", obs, ("blue", "red", "green"))
    base = np.asarray(obs["blocks"]["blue"]["position"])
    categories, targets = split_plan(plan.actions)
    releases = np.flatnonzero(categories == CATEGORIES.index("release"))
    first_of_each = [int(run[0]) for run in np.split(releases, np.flatnonzero(np.diff(releases) > 1) + 1)]
    assert len(plan.place_targets) == len(first_of_each) == 2
    for level, (target, step) in enumerate(zip(plan.place_targets, first_of_each), start=1):
        expected = np.array([base[0], base[1], base[2] + 0.04 * level + 0.005])
        np.testing.assert_allclose(target[:3], expected, atol=1e-9)
        tcp, _ = planner.ik.forward(targets[step, :7])
        np.testing.assert_allclose(tcp, expected, atol=1e-3)


def test_orders_start_with_the_default_and_cover_all_permutations():
    orders = block_orders()
    assert orders[0] == ("red", "green", "blue") and len(set(orders)) == 6


def test_bad_order_is_rejected(planner):
    obs = observation(sample_initial_blocks("stacking", 0), 0, LAYOUT)
    with pytest.raises(ValueError, match="order: must be a permutation"):
        planner.plan("stacking", obs, ("red", "red", "blue"))


def test_plan_is_deterministic_and_the_planner_seed_varies_grasp_yaws(planner):
    obs = observation(sample_initial_blocks("replacement", 9), 9, LAYOUT, PoseErrorConfig())
    a = planner.plan("replacement", obs)
    b = planner.plan("replacement", obs)
    np.testing.assert_array_equal(a.actions, b.actions)
    yaws = {tuple(np.round(planner.plan("replacement", obs, planner_seed=s).grasp_yaws, 6)) for s in range(8)}
    assert len(yaws) > 1


def test_unreachable_pose_raises_a_clear_error():
    ik = PandaIK()
    with pytest.raises(IKFailure, match="no IK solution"):
        ik.solve(np.array([1.5, 0.0, 0.02]), 0.0, np.zeros(7) + np.array([0, 0, 0, -1.5, 0, 1.5, 0]))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_plan_alone_carries_its_grasp_frames(planner, seed):
    """Forward kinematics of the plan's joint targets recovers where each block was estimated to be and
    the grasp's finger-axis yaw (what experiments/outcome_predictability.py's ``grasp_frame_plan``
    description uses), and the first release recovers the tower's base estimate."""
    from planner_client.ik import rotation_yaw

    layout = SceneLayout()
    true = sample_initial_blocks("stacking", seed, layout)
    obs = observation(true, seed, layout, PoseErrorConfig())
    order = ("green", "red", "blue")
    plan = planner.plan("stacking", obs, order)
    categories, targets = split_plan(plan.actions)
    joints = targets[:, :7]  # arm joints; the last two are the fingers

    def first_steps(name: str) -> list[int]:
        steps = np.flatnonzero(categories == CATEGORIES.index(name))
        return [int(run[0]) for run in np.split(steps, np.flatnonzero(np.diff(steps) > 1) + 1)]

    grasps, releases = first_steps("grasp"), first_steps("release")
    assert len(grasps) == len(releases) == 2
    for k, step in enumerate(grasps):
        pos, rot = planner.ik.forward(joints[step])
        estimate = np.asarray(obs["blocks"][order[k + 1]]["position"])
        assert np.linalg.norm(pos[:2] - estimate[:2]) < 1e-3
        assert abs(rotation_yaw(rot) - plan.grasp_yaws[k]) < 1e-3
    pos, _ = planner.ik.forward(joints[releases[0]])
    np.testing.assert_allclose(pos[:2], obs["blocks"][order[0]]["position"][:2], atol=1e-3)
