"""experiments.plan_reading_curves: every learner on the same fixed test set, nested training sets, resumable."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from experiments import plan_reading_curves
from firp.core.episodes import EpisodeRecord, consolidate, write_episode_part
from planner_client.loop import read_records
from tests.firp.model.test_plan_events import PANDA, overhead_camera, panda_plans
import pytest


def synthetic_dataset(root: Path, n: int = 90) -> Path:
    """Plans whose label is decided by where the hand ends (high or low), with the arm's chain, a camera's
    calibration and a view image per episode."""
    plans = panda_plans(n, 12, seed=5)
    from firp.core.kinematics import KinematicChain

    height = KinematicChain.from_dict(PANDA).tool_pose(plans[:, -1, 7:14].double().numpy())[:, 2, 3]
    labels = height > np.median(height)
    camera, _ = overhead_camera(32)
    for i in range(n):
        view = np.full((1, 32, 32, 3), 40 * int(labels[i]), np.uint8)
        write_episode_part(root / "parts", i, EpisodeRecord(np.zeros((1, 8, 8, 3), np.uint8), plans[i].numpy(),
                                                            np.zeros((12, 2)), bool(labels[i]), {}, view=view,
                                                            final_view=255 - view))
    out = root / "synthetic.h5"
    consolidate(root / "parts", out, {"fps": 4, "T": 12, "task": "stacking", "kinematics": PANDA,
                                      "camera_calibration": camera.to_dict()})
    return out


@pytest.mark.slow
def test_the_curves_put_every_learner_on_one_test_set_and_resume(tmp_path, capsys):
    data = synthetic_dataset(tmp_path)
    out = tmp_path / "curves.jsonl"
    argv = ["--data", str(data), "--sizes", "30", "60", "--learners", "raw:gb", "grasp_frame:gb", "events:gb", "events:net",
            "events_view:net", "events_final_view:net", "--out", str(out), "--threads", "1", "--min-steps", "10", "--plot", str(tmp_path / "c.png")]
    assert plan_reading_curves.main(argv) == 0
    records = read_records(out)
    assert {(r["learner"], r["size"]) for r in records} == {(lr, n) for lr in ("raw:gb", "grasp_frame:gb", "events:gb", "events:net",
                                                                                "events_view:net",
                                                                                "events_final_view:net") for n in (30, 60)}
    assert len({r["n_test"] for r in records}) == 1 and all(r["n_fit"] + r["n_valid"] == r["size"] for r in records)
    assert all(0.0 <= r["test_balanced_accuracy"] <= 1.0 and "command" in r for r in records)
    assert (tmp_path / "c.png").stat().st_size > 0
    assert plan_reading_curves.main(argv) == 0  # resumed: nothing trained again
    assert len(read_records(out)) == len(records)
    assert "| events:net |" in capsys.readouterr().out


def test_nested_training_sets_and_a_fixed_test_set():
    labels = np.array([0, 1] * 50)
    test, trains = plan_reading_curves.split_pool(labels, [20, 40], repeat=0)
    assert set(trains[20]) < set(trains[40]) and not set(trains[40]) & set(test) and len(test) == 20
    test_again, other = plan_reading_curves.split_pool(labels, [20], repeat=1)
    np.testing.assert_array_equal(test, test_again)
    assert set(other[20]) != set(trains[20])
    torch.manual_seed(0)
    assert json.dumps(plan_reading_curves.scores(np.array([0, 1, 1, 0]), np.array([0.2, 0.7, 0.6, 0.4]),
                                                 np.array([0, 1]), np.array([0.1, 0.9])))
