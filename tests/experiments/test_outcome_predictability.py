"""The scene descriptions of experiments/outcome_predictability.py, against hand-made scenes."""


import numpy as np
import pytest

from experiments import outcome_predictability as predictability

NAMES = ["red", "green", "blue"]


def stacking_attrs(estimate_shift=(0.0, 0.0)) -> dict:
    # order green (base), red, blue; red 10 cm east of the base, blue 10 cm north of it
    true = {"red": [0.6, 0.0, 0.02, 0.0], "green": [0.5, 0.0, 0.02, 0.0], "blue": [0.5, 0.1, 0.02, 0.0]}
    est = {c: {"position": [p[0] + estimate_shift[0], p[1] + estimate_shift[1], p[2]], "yaw": p[3]}
           for c, p in true.items()}
    return {"task": "stacking", "block_order": ["green", "red", "blue"],
            "true_initial_blocks": [true[c] for c in NAMES], "pose_estimates": est,
            "grasp_yaws": [np.pi / 2, 0.0], "place_targets": [[0.5, 0.0, 0.06, 0.0], [0.5, 0.0, 0.1, 0.0]]}


def test_grasp_frame_rotates_neighbours_into_each_grasp():
    f = predictability.grasp_frame_features(stacking_attrs(), NAMES, use_estimates=False)
    # base error (2); then per moved block: grasp offset (2), own yaw (2), 2 neighbours x 8
    assert f.shape == (2 + 2 * (4 + 2 * 8),)
    np.testing.assert_allclose(f[:2], 0.0)
    red = f[2:22]  # first move: red, grasp yaw 90 deg
    np.testing.assert_allclose(red[:2], 0.0, atol=1e-12)  # estimates exact: no grasp offset
    # base green is 10 cm west of red: world (-0.1, 0) -> grasp frame (0, +0.1) at yaw 90 deg
    np.testing.assert_allclose(red[4:6], [0.0, 0.1], atol=1e-12)
    assert red[8] == pytest.approx(0.1)
    assert red[11] == 1.0  # the base stays on the table
    # blue (picked after red) is at world (-0.1, 0.1) from red -> grasp frame (0.1, 0.1)
    np.testing.assert_allclose(red[12:14], [0.1, 0.1], atol=1e-12)
    assert red[19] == 1.0
    blue = f[22:]  # second move: blue, grasp yaw 0; red has been moved already
    np.testing.assert_allclose(blue[12:14], [0.1, -0.1], atol=1e-12)  # red's initial spot, world frame
    assert blue[19] == 0.0


def test_estimate_error_shows_as_grasp_offset_only_in_the_true_frame():
    attrs = stacking_attrs(estimate_shift=(0.003, 0.0))
    true_view = predictability.grasp_frame_features(attrs, NAMES, use_estimates=False)
    plan_view = predictability.grasp_frame_features(attrs, NAMES, use_estimates=True)
    np.testing.assert_allclose(true_view[:2], [0.003, 0.0])  # the tower's target vs its real base
    np.testing.assert_allclose(true_view[2:4], [0.0, -0.003], atol=1e-12)  # red's grasp, yaw 90 deg
    np.testing.assert_allclose(plan_view[:4], 0.0, atol=1e-12)  # the plan cannot see its own error
    # a common shift leaves every relative offset unchanged
    np.testing.assert_allclose(true_view[4:22], plan_view[4:22], atol=1e-12)


def test_raw_features_keep_the_recorded_layout():
    f = predictability.raw_features(stacking_attrs(), NAMES)
    assert f.shape == (12 + 3 + 3 + 3 + 6 + 4,)
    np.testing.assert_allclose(f[:4], [0.5, 0.0, 0.02, 0.0])  # green first: pick order


def test_candidates_are_described_as_the_loop_sees_and_plans_them():
    """The grasp-frame scorer describes loop candidates without executing them. Its description must be
    the scene the loop's own simulator starts (the same estimates and true blocks) and the plan the
    loop's planner makes for it: where the plan's grasp and release steps put the TCP (forward
    kinematics of the plan's joint targets) is where the description says the blocks are and go."""
    from firp.core.contract import CATEGORIES, split_plan
    from planner_client.embedded import EmbeddedSim
    from planner_client.ik import rotation_yaw
    from planner_client.tamp import TampPlanner

    from experiments import grasp_frame_scorer as scorer

    seed, orders = 100_003, [["red", "green", "blue"], ["blue", "red", "green"]]
    described = scorer.candidate_attrs("stacking", seed, orders)
    sim = EmbeddedSim(image_size=16)
    try:
        episode = sim.start("stacking", seed)
    finally:
        sim.close()
    planner = TampPlanner()
    for order, attrs in zip(orders, described):
        assert attrs["block_order"] == order
        assert attrs["pose_estimates"] == episode.observation["blocks"]
        np.testing.assert_array_equal(attrs["true_initial_blocks"], episode.true_blocks)
        categories, targets = split_plan(planner.plan("stacking", episode.observation, tuple(order)).actions)

        def starts(name: str) -> list[int]:
            steps = np.flatnonzero(categories == CATEGORIES.index(name))
            return [int(run[0]) for run in np.split(steps, np.flatnonzero(np.diff(steps) > 1) + 1)]

        base = np.asarray(attrs["pose_estimates"][order[0]]["position"])
        for k, (grasp, release) in enumerate(zip(starts("grasp"), starts("release"))):
            at_grasp, rot = planner.ik.forward(targets[grasp, :7])
            np.testing.assert_allclose(at_grasp, attrs["pose_estimates"][order[k + 1]]["position"], atol=1e-3)
            assert abs(rotation_yaw(rot) - attrs["grasp_yaws"][k]) < 1e-3
            at_release, _ = planner.ik.forward(targets[release, :7])
            np.testing.assert_allclose(at_release, attrs["place_targets"][k][:3], atol=1e-3)
            np.testing.assert_allclose(at_release, base + [0.0, 0.0, 0.04 * (k + 1) + 0.005], atol=1e-3)
    # two orders of one scene: the same scene, other picks
    assert described[0]["grasp_yaws"] != described[1]["grasp_yaws"] or \
        described[0]["place_targets"] != described[1]["place_targets"]


def test_wall_clearances_along_and_across_the_fingers():
    # box A: centre (0.5, -0.22), inner half extents 0.10; a block 3 cm east of the centre
    xy = np.array([0.53, -0.22])
    along, back, left, right = predictability.wall_clearances(xy, yaw=0.0)
    assert along == pytest.approx(0.07) and back == pytest.approx(0.13)
    assert left == pytest.approx(0.10) and right == pytest.approx(0.10)
    # fingers at 45 deg towards the north-east corner: the east wall is hit first, after 0.07 / cos 45
    assert predictability.wall_clearances(xy, yaw=np.pi / 4)[0] == pytest.approx(0.07 * np.sqrt(2))


def test_a_simulated_episodes_plan_is_made_again_exactly_and_described_by_forward_kinematics():
    """``plan_fk`` re-makes a simulated episode's plan from its cached attrs: it must be the plan that
    was executed (the planner is deterministic), and its description must place the grasps where the
    planner's estimates are."""
    import json

    from planner_client.tamp import PlannerConfig, TampPlanner
    from planner_client.collect import episode_order, simulate_episode
    from sim_worker.perception import PoseErrorConfig
    from sim_worker.scene import RenderConfig, SceneLayout
    from sim_worker.world import World

    with World(SceneLayout(), RenderConfig.for_task("stacking", 16, 16)) as world:
        records = [simulate_episode(world, TampPlanner(PlannerConfig()), "stacking", seed, episode_order(seed),
                                    PoseErrorConfig(), record_frames=False) for seed in (5, 6)]
    cached = json.loads(json.dumps(records[0].attrs))  # what the JSONL cache holds: no plan
    assert predictability.PLAN_KEY not in cached
    np.testing.assert_array_equal(predictability.episode_plan(cached).astype(np.float32), records[0].actions)
    recorded = {**cached, predictability.PLAN_KEY: records[0].actions}  # a dataset episode
    other = {**records[1].attrs, predictability.PLAN_KEY: records[1].actions}
    X = predictability.plan_fk_features([(cached, True), (recorded, True), (other, False)])
    assert X.shape[1] > 20  # the columns that differ between the two scenes
    np.testing.assert_allclose(X[0], X[1], atol=1e-5)  # float32 recorded plan vs the re-made float64 one
    assert np.abs(X[0] - X[2]).max() > 1e-3
