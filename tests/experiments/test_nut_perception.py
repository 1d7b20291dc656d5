"""The nut-assembly perception analysis: the grip read in the nut's frame, the state layout check, a full run."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from experiments.nut_perception import (
    NUT_QPOS,
    choice_columns,
    grip_on_handle,
    grip_seen_at,
    handle_centres,
    main,
    pose_targets,
    read,
    true_nut_poses,
)
from firp.core.contract import CATEGORY_INDEX, make_plan
from firp.core.episodes import EpisodeRecord
from firp.core.episodes.writer import consolidate, write_episode_part
from firp.model.plan_geometry import pick_events

HANDLE = np.array([0.054, 0.0])
T = 12


def test_a_grip_at_the_handles_centre_reads_zero_and_moves_with_the_hand():
    nut_xy, nut_yaw = np.array([[0.1, 0.2]]), np.array([0.3])
    centre = handle_centres(nut_xy, nut_yaw, HANDLE)
    assert np.allclose(np.linalg.norm(centre - nut_xy), 0.054)
    across = nut_yaw + math.pi / 2  # axis 0: the fingers close across the handle
    assert np.allclose(grip_on_handle(centre, across, np.array([0]), nut_xy, nut_yaw, HANDLE), 0.0, atol=1e-9)
    outwards = centre + 0.005 * np.array([[math.cos(0.3), math.sin(0.3)]])
    sideways = centre + 0.002 * np.array([[-math.sin(0.3), math.cos(0.3)]])
    assert np.allclose(grip_on_handle(outwards, across, np.array([0]), nut_xy, nut_yaw, HANDLE), [[5.0, 0.0, 0.0]])
    assert np.allclose(grip_on_handle(sideways, across, np.array([0]), nut_xy, nut_yaw, HANDLE), [[0.0, 2.0, 0.0]])
    # axis 1 closes along the handle; a hand turned half a turn is the same grip, 2 degrees more is misaligned
    along = nut_yaw + math.pi + math.radians(2.0)
    assert np.allclose(grip_on_handle(centre, along, np.array([1]), nut_xy, nut_yaw, HANDLE), [[0.0, 0.0, 2.0]])


def test_the_nuts_yaw_comes_from_its_recorded_quaternion():
    yaws = np.array([0.7, -2.5, 3.0])
    quats = np.stack([np.cos(yaws / 2), 0 * yaws, 0 * yaws, np.sin(yaws / 2)], axis=1)
    states = np.zeros((3, 44))
    states[:, NUT_QPOS.start + 3:NUT_QPOS.stop] = quats
    _, yaw = true_nut_poses(states, np.zeros((3, 2)))
    assert np.allclose(yaw, yaws)


def test_a_state_layout_that_is_not_the_nuts_is_refused():
    states = np.zeros((2, 44))
    states[:, NUT_QPOS.start:NUT_QPOS.start + 2] = [[0.1, 0.2], [0.1, 0.2]]
    estimates = np.array([[0.101, 0.2], [0.3, 0.2]])
    with pytest.raises(ValueError, match="episode 1's nut .* 20.0 cm from the planner's estimate"):
        true_nut_poses(states, estimates)
    xy, _ = true_nut_poses(states[:1], estimates[:1])
    assert np.allclose(xy, [[0.1, 0.2]])


def test_the_planners_choice_label_becomes_numbers():
    assert choice_columns("SquareNut:1:d:q1:O") == [1.0, 1.0, 1.0, 10.0]
    assert choice_columns("SquareNut:0:l:q0:I") == [0.0, 0.0, 0.0, -8.0]


@pytest.fixture(scope="module")
def tiny_nut_dataset(tmp_path_factory):
    """24 nut_assembly-shaped episodes: each plan grasps where the nut's handle is (FK of its joints), the nut
    really lies 3 mm away from the planner's estimate, and the plan fails iff its grip misses by over 3 mm."""
    root = tmp_path_factory.mktemp("nutdata")
    rng = np.random.default_rng(0)
    categories = np.full(T, CATEGORY_INDEX["move"])
    categories[4:6], categories[8:10] = CATEGORY_INDEX["grasp"], CATEGORY_INDEX["release"]
    for i in range(24):
        joints = np.array([0.0, 0.2, 0.0, -2.6, 0.0, 2.9, 0.785]) + rng.normal(0, 0.05, 7)
        targets = np.concatenate([np.tile(joints, (T, 1)), np.full((T, 2), 0.04)], axis=1)
        plan = make_plan(categories, targets).astype(np.float32)
        events = pick_events(torch.as_tensor(plan[None], dtype=torch.float64), None, max_picks=1)
        grasp_xy, finger_yaw = events["grasp_pos"][0, 0, :2].numpy(), float(events["grasp_yaw"][0, 0])
        nut_yaw = finger_yaw - math.pi / 2  # axis 0
        miss = rng.uniform(-0.006, 0.006)  # how far outwards of the handle's centre the fingers close
        direction = np.array([math.cos(nut_yaw), math.sin(nut_yaw)])
        nut_xy = grasp_xy - (0.054 + miss) * direction
        states = np.zeros((T, 44))
        states[:, NUT_QPOS] = [*nut_xy, 0.83, math.cos(nut_yaw / 2), 0.0, 0.0, math.sin(nut_yaw / 2)]
        estimate = {"position": [nut_xy[0] + 0.003, nut_xy[1], 0.83], "yaw": nut_yaw}
        frames = rng.integers(0, 255, (T, 32, 32, 3), dtype=np.uint8)
        attrs = {"seed": i, "choice": f"SquareNut:0:d:q0:{'moOiI'[i % 5]}", "block_order": ["SquareNut"],
                 "pose_estimates": {"SquareNut": estimate},
                 "scene": {"handle_offset": HANDLE.tolist(), "peg": [0.23, 0.1, 0.85]}}
        write_episode_part(root / "parts", i, EpisodeRecord(frames, plan, states, abs(miss) <= 0.003, attrs))
    consolidate(root / "parts", root / "nut.h5", {"fps": 4, "T": T, "task": "nut_assembly"})
    return root / "nut.h5"


def test_the_analysis_reads_a_nut_dataset_measures_and_draws(tiny_nut_dataset, tmp_path):
    out, picture = tmp_path / "nut.json", tmp_path / "nut.png"
    assert main(["--data", str(tiny_nut_dataset), "--repeats", "2", "--cnn-epochs", "2", "--out", str(out),
                 "--plot", str(picture), "--no-progress"]) == 0
    result = json.loads(out.read_text())
    assert result["episodes"] == 24 and len(result["rows"]) == 2
    for key in ("choice", "plan_geometry", "choice_and_true_grip", "true_grip_seen_with_error@3",
                "choice_and_image_located_grip", "plan_geometry_and_image_located_grip"):
        assert 0.0 <= result["classifiers"][key][0] <= 1.0
    # the planner's estimate lies exactly 3 mm off along x: its handle error is 3 mm on every test episode
    assert result["localisation"]["planner"]["handle_centre_rmse_mm"][0] == pytest.approx(3.0)
    assert result["localisation"]["planner"]["yaw_rmse_deg"][0] == pytest.approx(0.0, abs=1e-9)
    for name in ("frozen_features_ridge", "small_cnn", "small_cnn_cross_fitted"):
        assert result["localisation"][name]["handle_centre_rmse_mm"][0] > 0.0
    # the 3 mm estimate error shows as the difference between the true and the believed grip
    error = result["perception_error_at_the_grip"]
    assert math.hypot(error["along_mm_rms"], error["across_mm_rms"]) == pytest.approx(3.0)
    assert error["misalignment_deg_rms"] == pytest.approx(0.0, abs=1e-6)
    assert picture.stat().st_size > 10_000


def test_the_grip_read_where_the_nut_truly_lies_is_the_true_grip(tiny_nut_dataset):
    data = read(tiny_nut_dataset)
    np.testing.assert_allclose(grip_seen_at(data, pose_targets(data)), data["true_grip"], atol=1e-6)
    moved = pose_targets(data) + np.array([0.002, 0.0, 0.0, 0.0])  # the nut located 2 mm off along x
    assert not np.allclose(grip_seen_at(data, moved), data["true_grip"], atol=1.0)


def test_a_dataset_of_another_task_is_refused(tiny_dataset, tmp_path):
    with pytest.raises(ValueError, match="--data: a nut_assembly dataset is needed"):
        main(["--data", str(tiny_dataset), "--out", str(tmp_path / "x.json"), "--cnn-epochs", "0"])
