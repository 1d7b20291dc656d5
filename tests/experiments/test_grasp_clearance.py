"""The grasp-clearance analysis: the hand's clearance read from recorded plans, a rule, tabular learners, a plot."""

from __future__ import annotations

import json

import numpy as np
import pytest

from experiments.grasp_clearance import (by_bins, clearance_and_heights, describe, main, sized_clearance_and_heights,
                                         true_halves)
from firp.core.episodes import EpisodeDataset

pytestmark = pytest.mark.slow  # make test-fast leaves this module out


def test_bins_count_every_plan_once_and_their_success_rates():
    finger = np.array([-0.02, -0.007, -0.001, 0.002, 0.007, 0.015, 0.05, 0.03])
    labels = np.array([False, False, True, True, True, True, True, False])
    bins = by_bins(finger, labels)
    assert sum(b["plans"] for b in bins) == len(finger)
    assert bins[0] == {"from_m": None, "to_m": -0.01, "plans": 1, "success_rate": 0.0}
    assert bins[-1]["plans"] == 2 and bins[-1]["success_rate"] == 0.5


def test_the_analysis_reads_a_recorded_dataset(tiny_dataset, tmp_path):
    out, picture = tmp_path / "clearance.json", tmp_path / "clearance.png"
    assert main(["--data", str(tiny_dataset), "--repeats", "2", "--fractions", "0.5", "--out", str(out),
                 "--plot", str(picture)]) == 0
    result = json.loads(out.read_text())
    assert result["episodes"] == 20 and len(result["rows"]) == 2
    assert sum(b["plans"] for b in result["bins"]) == 20
    for key in ("finger_clearance_rule", "description_gradient_boosting", "clearance_gradient_boosting",
                "description_and_clearance_gradient_boosting", "clearance_mlp", "description_mlp",
                "clearance_and_heights_mlp", "clearance_and_heights_gradient_boosting",
                "sized_clearance_and_heights_mlp", "sized_clearance_and_heights_gradient_boosting",
                "description_and_clearance_gradient_boosting@0.5", "clearance_mlp@0.5"):
        assert 0.0 <= result["mean_std"][key][0] <= 1.0
    shares = [result["rows"][0][f"gradient_boosting_importance_{part}"] for part in ("clearance", "heights",
                                                                                   "other_grasp_frame")]
    assert all(0.0 <= share <= 1.0 for share in shares) and sum(shares) == pytest.approx(1.0)
    assert picture.stat().st_size > 10_000
    # our world's records hold no cube sizes: no yardstick with the true sizes
    assert "true_sized_clearance_and_heights_mlp" not in result["mean_std"]
    with EpisodeDataset(tiny_dataset) as ds:
        actions = np.stack([ds.actions(name) for name in ds.demo_names])
        assert true_halves(ds, ds.demo_names, 3) is None
    sized = sized_clearance_and_heights(actions, 3)
    assert sized.shape == (20, 27) and np.array_equal(sized[:, 18:], clearance_and_heights(actions, 3)[:, 18:])
    description, clearance, finger = describe(actions, 3)
    assert clearance.shape == (20, 18)
    with_heights = clearance_and_heights(actions, 3)
    assert with_heights.shape == (20, 27) and np.array_equal(with_heights[:, :18], clearance)
    # each plan's smallest finger clearance is one of its present picks' pad or finger columns
    per_pick = clearance.reshape(20, 3, 6)[:, :, :2]
    assert np.all(np.isclose(per_pick.reshape(20, -1), finger[:, None]).any(axis=1) | np.isinf(finger))


def test_chosen_learning_curves_are_measured_drawn_and_reproducible(tiny_dataset, tmp_path):
    out, picture = tmp_path / "curves.json", tmp_path / "curves.png"
    argv = ["--data", str(tiny_dataset), "--repeats", "2", "--fractions", "0.5", "0.75",
            "--curves", "description_and_clearance:mlp", "clearance:gradient_boosting", "--out", str(out),
            "--curve-plot", str(picture)]
    assert main(argv) == 0
    result = json.loads(out.read_text())
    assert [c["name"] for c in result["curves"]] == ["description_and_clearance:mlp", "clearance:gradient_boosting"]
    for c in result["curves"]:
        sizes = [p["training_episodes"] for p in c["points"]]
        assert len(sizes) == 3 and sizes == sorted(sizes) and sizes[-1] == result["training_episodes"]
        name = c["name"].replace(":", "_")
        assert c["points"][0]["mean"] == result["mean_std"][f"{name}@0.5"][0]
        assert c["points"][-1]["mean"] == result["mean_std"][name][0]
    assert "description_and_clearance_mlp@0.75" in result["rows"][0]
    assert "clearance_mlp@0.5" not in result["rows"][0]  # only the curves asked for
    assert picture.stat().st_size > 10_000
    assert result["command"] == "python -m experiments.grasp_clearance " + " ".join(argv)


@pytest.mark.parametrize("flag, value, rule", [("--curves", "clearance:forest", "LEARNER one of"),
                                               ("--curves", "pixels:mlp", "INPUT one of"),
                                               ("--fractions", "1.0", "strictly between 0 and 1"),
                                               ("--first", "5", "at least 10"),
                                               ("--first", "25", "fewer than 25")])
def test_bad_curves_and_fractions_name_the_flag_and_rule(tiny_dataset, tmp_path, capsys, flag, value, rule):
    with pytest.raises(SystemExit):
        main(["--data", str(tiny_dataset), "--out", str(tmp_path / "x.json"), flag, value])
    err = capsys.readouterr().err
    assert flag in err and rule in err


def test_first_reads_the_first_episodes_only(tiny_dataset, tmp_path):
    out = tmp_path / "first.json"
    assert main(["--data", str(tiny_dataset), "--first", "16", "--repeats", "1", "--fractions", "0.5",
                 "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["episodes"] == 16 and sum(b["plans"] for b in result["bins"]) == 16
    with EpisodeDataset(tiny_dataset) as ds:
        labels = ds.success_labels()[:16]
    assert [b["plans"] for b in result["bins"]] and result["training_episodes"] + result["validation_episodes"] < 16
    rate = sum(b["plans"] * b["success_rate"] for b in result["bins"] if b["plans"]) / 16
    assert rate == pytest.approx(labels.mean())


class _RecordedStacking:
    """What robosuite's stacking records per episode: the block order (the tower's base first) and the scene."""

    def demo_attrs(self, name):
        orders = {"a": ["cubeC", "cubeB", "cubeA"], "b": ["cubeB", "cubeA", "cubeC"]}
        return {"block_order": orders[name], "scene": {"cube_half": {"cubeA": 0.02, "cubeB": 0.025, "cubeC": 0.02}}}


def test_true_halves_follow_each_episodes_block_order_and_feed_the_yardstick(tiny_dataset):
    halves = true_halves(_RecordedStacking(), ["a", "b"], 3)
    np.testing.assert_array_equal(halves, [[0.02, 0.025, 0.02, 0.0], [0.025, 0.02, 0.02, 0.0]])
    with EpisodeDataset(tiny_dataset) as ds:
        actions = np.stack([ds.actions(name) for name in ds.demo_names[:2]])
    sized = sized_clearance_and_heights(actions, 3, halves)
    assert sized.shape == (2, 27) and not np.array_equal(sized, sized_clearance_and_heights(actions, 3))


def test_the_true_sizes_yardstick_needs_recorded_sizes(tiny_dataset, tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--data", str(tiny_dataset), "--out", str(tmp_path / "x.json"), "--curves",
              "true_sized_clearance_and_heights:mlp"])
    err = capsys.readouterr().err
    assert "--curves" in err and "records no block order and cube sizes" in err


def test_a_missing_dataset_names_the_flag(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--data", str(tmp_path / "missing.h5"), "--out", str(tmp_path / "x.json")])
    assert "--data" in capsys.readouterr().err
