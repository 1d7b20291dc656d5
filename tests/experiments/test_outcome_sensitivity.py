"""The ceiling analysis of experiments/outcome_sensitivity.py, against hand-worked records."""


import numpy as np
import pytest

from experiments import outcome_sensitivity as sensitivity

ORDERS = [("a", "b"), ("b", "a")]


def record(seed: int, success: bool, perturbed: list[bool], order=ORDERS[0]) -> dict:
    return {"seed": seed, "order": list(order), "success": success, "reason": "",
            "perturbed_success": perturbed, "perturbed_reasons": [""] * len(perturbed)}


def test_ceiling_threshold_by_hand():
    # p = 0, 1/4, 3/4, 1 over four plans (4 perturbations each), outcomes F, T, F, T
    records = [record(0, False, [False] * 4), record(1, True, [True, False, False, False]),
               record(2, False, [True, True, True, False]), record(3, True, [True] * 4)]
    out = sensitivity.analyse(records)
    # success when p >= 1/8 -> [F, T, T, T]: TPR 1, TNR 1/2 -> 0.75; p >= 7/8 -> [F, F, F, T]: 1/2, 1 -> 0.75;
    # p >= 1/2 -> [F, F, T, T]: 1/2, 1/2 -> 0.5. The tie goes to the cut nearer 0.5, then the lower one.
    assert out["ceiling_balanced_accuracy_best_threshold"] == 0.75
    assert out["ceiling_threshold"] == 0.125


def test_analyse_counts_flips_and_the_ceiling():
    records = [record(0, True, [True, True]),      # stable success, p = 1
               record(1, False, [False, False]),   # stable failure, p = 0
               record(2, True, [False, True]),     # flips, p = 1/2
               record(3, False, [True, False])]    # flips, p = 1/2
    out = sensitivity.analyse(records)
    assert out["plans"] == 4 and out["perturbations_per_plan"] == 2
    assert out["success_rate"] == 0.5
    assert out["perturbed_success_rate"] == 0.5
    assert out["plans_whose_outcome_flips_under_some_perturbation"] == 0.5
    assert out["perturbed_runs_disagreeing_with_unperturbed"] == 0.25
    assert out["p_histogram"] == {"0/2": 1, "1/2": 2, "2/2": 1}
    # best: success when p > 0 -> predicts T for seeds 0, 2, 3: TPR 1, TNR 1/2 -> 0.75
    assert out["ceiling_balanced_accuracy_best_threshold"] == 0.75


def test_a_chaotic_outcome_puts_the_ceiling_at_chance():
    rng = np.random.default_rng(0)
    records = [record(i, bool(rng.random() < 0.5), [bool(v) for v in rng.random(8) < 0.5]) for i in range(400)]
    out = sensitivity.analyse(records)
    assert abs(out["ceiling_balanced_accuracy_5fold_threshold"] - 0.5) < 0.08


def test_perturbations_are_seeded_and_leave_height_alone():
    blocks = np.array([[0.5, 0.1, 0.02, 0.3], [0.4, -0.1, 0.02, -0.2]])
    a = sensitivity.perturbed_blocks(blocks, seed=7, k=0, xy_std_m=0.001, yaw_std_deg=1.0)
    b = sensitivity.perturbed_blocks(blocks, seed=7, k=0, xy_std_m=0.001, yaw_std_deg=1.0)
    c = sensitivity.perturbed_blocks(blocks, seed=7, k=1, xy_std_m=0.001, yaw_std_deg=1.0)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    np.testing.assert_array_equal(a[:, 2], blocks[:, 2])
    assert np.abs(a[:, :2] - blocks[:, :2]).max() < 0.006  # 6 std
    draws = np.stack([sensitivity.perturbed_blocks(blocks, 1, k, 0.001, 1.0) for k in range(2000)])
    assert np.std(draws[:, :, 0] - blocks[:, 0]) == pytest.approx(0.001, rel=0.1)
    assert np.degrees(np.std(draws[:, :, 3] - blocks[:, 3])) == pytest.approx(1.0, rel=0.1)


def test_loop_ceiling_by_hand():
    records = [
        # seed 0: first candidate fails (p = 0), second succeeds (p = 1): ceiling picks it
        record(0, False, [False, False], ORDERS[0]), record(0, True, [True, True], ORDERS[1]),
        # seed 1: both fail; the first looks better (p = 1/2)
        record(1, False, [True, False], ORDERS[0]), record(1, False, [False, False], ORDERS[1]),
        # seed 2: first succeeds (p = 1/2), second fails (p = 0)
        record(2, True, [True, False], ORDERS[0]), record(2, False, [False, False], ORDERS[1]),
    ]
    out = sensitivity.analyse_loop(records, ORDERS, None)
    assert out["trials"] == 3 and out["candidates_per_trial"] == 2
    assert out["tamp_alone_success"] == pytest.approx(1 / 3, abs=1e-3)
    assert out["oracle_success"] == pytest.approx(2 / 3, abs=1e-3)
    assert out["ceiling_pick_highest_p_success"] == pytest.approx(2 / 3, abs=1e-3)
    # accept p >= 0.5: seed 0 -> candidate 1 (ok), seed 1 -> candidate 0 (fail), seed 2 -> candidate 0 (ok)
    assert out["ceiling_paper_rule_best_threshold_success"] == pytest.approx(2 / 3, abs=1e-3)
    assert "firp_candidate_auc" not in out


def test_loop_comparison_with_firp_scores_splits_stable_and_unstable(tmp_path):
    import json

    records = [
        record(0, False, [False, False], ORDERS[0]), record(0, True, [True, True], ORDERS[1]),    # stable
        record(1, False, [True, False], ORDERS[0]), record(1, True, [False, True], ORDERS[1]),    # unstable
        record(2, True, [True, True], ORDERS[0]), record(2, False, [False, False], ORDERS[1]),    # stable
        record(3, True, [True, False], ORDERS[0]), record(3, False, [True, False], ORDERS[1]),    # unstable
    ]
    firp = [[0.2, 0.9], [0.8, 0.1], [0.7, 0.3], [0.3, 0.6]]  # right on the stable ones, wrong on the others
    success = [[False, True], [False, True], [True, False], [True, False]]
    scores = tmp_path / "scores.jsonl"
    scores.write_text("".join(json.dumps({"seed": s, "scores": f, "success": ok, "model": {"threshold": 0.5}}) + "\n"
                              for s, (f, ok) in enumerate(zip(firp, success))))
    out = sensitivity.analyse_loop(records, ORDERS, scores)
    assert out["recorded_outcomes_reproduced"] is True
    # FIRP's rule at 0.5: seed 0 -> cand 1 ok, seed 1 -> cand 0 fail, seed 2 -> cand 0 ok, seed 3 -> cand 1 fail
    assert out["firp_paper_rule_bundle_threshold_success"] == 0.5
    assert out["firp_on_stable_candidates"] == {"candidates": 4, "roc_auc": 1.0,
                                                "balanced_accuracy_at_bundle_threshold": 1.0}
    assert out["firp_on_unstable_candidates"] == {"candidates": 4, "roc_auc": 0.0,
                                                  "balanced_accuracy_at_bundle_threshold": 0.0}


def test_loop_comparison_refuses_records_of_other_outcomes(tmp_path):
    import json

    records = [record(0, False, [False], ORDERS[0]), record(0, True, [True], ORDERS[1])]
    scores = tmp_path / "scores.jsonl"
    scores.write_text(json.dumps({"scores": [0.1, 0.9], "success": [True, True], "model": {"threshold": 0.5}}) + "\n")
    with pytest.raises(SystemExit, match="differ"):
        sensitivity.analyse_loop(records, ORDERS, scores)
