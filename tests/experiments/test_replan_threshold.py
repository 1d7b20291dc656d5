"""The replay of the replanning loop in experiments/replan_threshold.py, against hand-worked trials."""


import numpy as np
import pytest

from experiments import replan_threshold as replan

# three trials, three candidates each (in the loop's order)
SCORES = np.array([[0.2, 0.7, 0.9],
                   [0.6, 0.1, 0.3],
                   [0.1, 0.2, 0.4]])
SUCCESS = np.array([[False, True, True],
                    [False, False, True],
                    [False, True, False]])


@pytest.mark.parametrize("threshold, rate, plans", [
    # trial 0 -> candidate 1 (ok); trial 1 -> candidate 0 (fail); trial 2 -> none pass, last (fail)
    (0.5, 1 / 3, (2 + 1 + 3) / 3),
    # everything passes at 0: the first candidate every time
    (0.0, 0 / 3, 1.0),
    # nothing passes at 0.95: the last candidate every time (ok, ok, fail)
    (0.95, 2 / 3, 3.0),
    # 0.35: trial 0 -> cand 1 (ok), trial 1 -> cand 0 (fail), trial 2 -> cand 2 (fail)
    (0.35, 1 / 3, (2 + 1 + 3) / 3),
])
def test_replan_success_follows_the_loops_rule(threshold, rate, plans):
    got_rate, got_plans = replan.replan_success(SCORES, SUCCESS, threshold)
    assert got_rate == pytest.approx(rate)
    assert got_plans == pytest.approx(plans)


def test_threshold_free_policies():
    p = replan.policies(SCORES, SUCCESS)
    assert p["tamp_alone"] == 0.0
    assert p["oracle"] == 1.0
    assert p["best_score"] == pytest.approx(1 / 3)  # argmax: cand 2 (ok), cand 0 (fail), cand 2 (fail)
    assert p["any_candidate_mean"] == pytest.approx(4 / 9)


def test_choose_threshold_prefers_the_best_rate_then_fewer_plans():
    curve = [{"threshold": 0.2, "success_rate": 0.5, "plans_scored": 1.0},
             {"threshold": 0.4, "success_rate": 0.7, "plans_scored": 2.5},
             {"threshold": 0.6, "success_rate": 0.7, "plans_scored": 2.0},
             {"threshold": 0.8, "success_rate": 0.7, "plans_scored": 2.0}]
    assert replan.choose_threshold(curve) == 0.6


def test_rescoring_refuses_records_of_another_task_or_split(tmp_path):
    """(That rescoring gives back the shipped bundle's recorded scores, and that the recorded outcomes
    are the simulator's, is checked on the committed records in tests/golden/test_shipped_bundles.py.)"""
    import json

    record = {"trial": 0, "seed": 100_000, "task": "stacking", "split": "test", "orders": [["red", "green", "blue"]],
              "scores": [0.5], "success": [True], "model": {"threshold": 0.5}}
    src = tmp_path / "stacking-test.jsonl"
    src.write_text(json.dumps(record) + "\n")
    from firp.core.bundle_format import shipped_bundle_dir

    bundle = shipped_bundle_dir("stacking")
    with pytest.raises(SystemExit, match="expected stacking/calibration"):
        replan.rescore("stacking", "calibration", src, bundle, tmp_path / "x.jsonl", progress=False)
