"""The grasp-clearance analysis: the hand's clearance read from recorded plans, a rule, tabular learners, a plot."""

from __future__ import annotations

import json

import numpy as np
import pytest

from experiments.grasp_clearance import by_bins, describe, main
from firp.core.episodes import EpisodeDataset


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
                "description_and_clearance_gradient_boosting@0.5", "clearance_mlp@0.5"):
        assert 0.0 <= result["mean_std"][key][0] <= 1.0
    assert picture.stat().st_size > 10_000
    with EpisodeDataset(tiny_dataset) as ds:
        actions = np.stack([ds.actions(name) for name in ds.demo_names])
    description, clearance, finger = describe(actions, 3)
    assert clearance.shape == (20, 18)
    # each plan's smallest finger clearance is one of its present picks' pad or finger columns
    per_pick = clearance.reshape(20, 3, 6)[:, :, :2]
    assert np.all(np.isclose(per_pick.reshape(20, -1), finger[:, None]).any(axis=1) | np.isinf(finger))


def test_a_missing_dataset_names_the_flag(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--data", str(tmp_path / "missing.h5"), "--out", str(tmp_path / "x.json")])
    assert "--data" in capsys.readouterr().err
