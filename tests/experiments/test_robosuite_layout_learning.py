"""The layout learning curve: features read from a robosuite episode's record, the curve on synthetic
episodes whose label a known layout rule decides, and the command run on records already simulated."""

from __future__ import annotations

import json

import numpy as np
import pytest

from experiments.robosuite_layout_learning import (INPUTS, LEARNERS, clutter_features, feature_table, fit,
                                                   gain_per_doubling, learning_curve, main)

pytestmark = pytest.mark.slow  # make test-fast leaves this module out

OBJECTS = ["Bread", "Can", "Cereal", "Milk"]
SCENE = {"bin1": [0.1, -0.25, 0.8], "bin_size": [0.39, 0.49],
         "objects": {"Bread": {"half": [0.024, 0.02, 0.024]}, "Can": {"half": [0.026, 0.026, 0.04]},
                     "Cereal": {"half": [0.05, 0.015, 0.075]}, "Milk": {"half": [0.02, 0.02, 0.072]}}}


def record(seed: int, rng: np.random.Generator) -> dict:
    """A pick & place episode: a random order and layout in the first bin; it fails when the first object
    picked stands within 6 cm of one still in the bin (the rule a scorer must learn from the layout)."""
    order = list(rng.permutation(OBJECTS))
    positions = {n: [0.1 + rng.uniform(-0.15, 0.15), -0.25 + rng.uniform(-0.2, 0.2), 0.85] for n in OBJECTS}
    first = np.asarray(positions[order[0]][:2])
    crowded = min(np.linalg.norm(first - np.asarray(positions[n][:2])) for n in order[1:]) < 0.06
    faces = "".join(str(int(v)) for v in rng.integers(0, 2, 4))
    heights = "".join("h" if v else "c" for v in rng.integers(0, 2, 4))
    return {"seed": seed, "success": not crowded, "block_order": order,
            "choice": f"{'-'.join(order)}:{faces}:{heights}",
            "pose_estimates": {n: {"position": positions[n], "yaw": float(rng.uniform(-np.pi, np.pi))}
                               for n in OBJECTS},
            "scene": SCENE}


def records(n: int, seed: int = 0) -> list[dict]:
    rng = np.random.default_rng(seed)
    return [record(i, rng) for i in range(n)]


def test_clutter_reads_each_picks_nearest_neighbour_still_in_the_bin_and_its_wall():
    r = record(0, np.random.default_rng(0))
    r["block_order"] = ["Can", "Milk", "Bread", "Cereal"]
    r["pose_estimates"] = {"Can": {"position": [0.1, -0.25, 0.85], "yaw": 0.0},
                           "Milk": {"position": [0.15, -0.25, 0.85], "yaw": 0.0},
                           "Bread": {"position": [0.1, -0.10, 0.85], "yaw": 0.0},
                           "Cereal": {"position": [0.25, -0.25, 0.85], "yaw": 0.0}}
    out = clutter_features(r, OBJECTS)
    assert len(out) == 4 * 4
    gap, height, near, wall = out[:4]  # the can: the milk carton 5 cm away, 14.4 cm tall; bin half 0.195
    assert gap == pytest.approx(0.05) and height == pytest.approx(0.144) and near == 1.0  # only the milk within 8 cm
    assert wall == pytest.approx(0.195)  # the bin's centre: the nearest wall is across its short side
    assert out[12:] == [1.0, 0.0, 0.0, pytest.approx(0.195 - 0.15)]  # the last pick: nothing left beside it


def test_feature_tables_grow_with_what_each_input_is_told():
    rs = records(5)
    widths = [feature_table(rs, name).shape for name in INPUTS]
    assert widths == [(5, 12), (5, 12 + 4 * 7), (5, 12 + 4 * 7 + 16)]


def test_the_curve_finds_the_layout_rule_only_in_the_inputs_that_carry_the_layout():
    rs = records(600)
    curves = learning_curve(rs, [50, 400], repeats=2)
    assert set(curves) == set(LEARNERS)
    for by_input in curves.values():
        assert set(by_input) == set(INPUTS)
        for curve in by_input.values():
            assert [int(s) for s in curve] == pytest.approx([50, 400], abs=2)  # stratified subsets of the pool
            assert all(len(cell["repeats"]) == 2 for cell in curve.values())
    for learner, by_input in curves.items():
        best = {name: list(curve.values())[-1]["mean"] for name, curve in by_input.items()}
        assert best["choice"] < 0.65, learner  # the order alone does not tell whether the first pick is crowded
        assert best["choice_and_clutter"] > best["choice"] + 0.15, learner  # the nearest gap is the rule itself
    gb = curves["gradient_boosting"]["choice_and_clutter"]
    assert list(gb.values())[-1]["mean"] > 0.9 and list(gb.values())[-1]["mean"] > list(gb.values())[0]["mean"]


def test_fit_names_the_learners_it_knows():
    X, y = np.random.default_rng(0).normal(size=(20, 3)), np.arange(20) % 2 == 0
    for learner in LEARNERS:
        assert fit(learner, X, y, 0).predict_proba(X).shape == (20, 2)
    with pytest.raises(ValueError, match="learner"):
        fit("svm", X, y, 0)


def test_gain_per_doubling_is_the_slope_in_log2_of_the_training_size():
    curve = {"100": {"mean": 0.6}, "200": {"mean": 0.65}, "400": {"mean": 0.7}}
    assert gain_per_doubling(curve) == pytest.approx(0.05)


def test_the_command_draws_the_curve_from_episodes_already_simulated(tmp_path, capsys):
    jsonl = tmp_path / "episodes.jsonl"
    rs = records(240)
    rs[3] = {"seed": 3, "unplannable": "no reachable choice"}
    jsonl.write_text("".join(json.dumps(r) + "\n" for r in rs))
    report = tmp_path / "layout.json"
    assert main(["--task", "pick_place", "--episodes", "240", "--sizes", "40", "120", "--repeats", "2",
                 "--ceiling", "0.92", "--target", "0.922", "--out", str(jsonl), "--report", str(report)]) == 0
    result = json.loads(report.read_text())
    assert result["unplannable"] == 1 and result["successes"] + result["failures"] == 239
    assert set(result["curves"]) == set(LEARNERS) and set(result["gain_per_doubling"]["mlp"]) == set(INPUTS)
    assert report.with_suffix(".png").stat().st_size > 0
    assert "choice_and_clutter" in capsys.readouterr().out


def test_the_command_refuses_bad_arguments(tmp_path):
    with pytest.raises(SystemExit):
        main(["--task", "pick_place", "--episodes", "0", "--out", str(tmp_path / "e.jsonl"),
              "--report", str(tmp_path / "r.json")])
    with pytest.raises(SystemExit):
        main(["--task", "pick_place", "--episodes", "10", "--out", str(tmp_path / "e.jsonl")])  # no --report
    jsonl = tmp_path / "one_class.jsonl"
    jsonl.write_text("".join(json.dumps({**r, "success": True}) + "\n" for r in records(20)))
    with pytest.raises(SystemExit):
        main(["--task", "pick_place", "--episodes", "20", "--out", str(jsonl), "--report", str(tmp_path / "r.json")])
