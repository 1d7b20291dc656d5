"""Metrics against hand-computed values, including the degenerate cases the definitions fix."""

import numpy as np
import pytest

from firp.metrics import (
    balanced_accuracy,
    calibration_bins,
    choose_threshold,
    expected_calibration_error,
    reliability_diagram,
)


# balanced accuracy ---------------------------------------------------------------------------


def test_balanced_accuracy_is_the_mean_of_tpr_and_tnr():
    # TP = 2 of 3 successes, TN = 1 of 2 failures: (2/3 + 1/2) / 2 = 7/12
    assert balanced_accuracy([1, 1, 1, 0, 0], [1, 0, 1, 0, 1]) == pytest.approx(7 / 12)
    assert balanced_accuracy([True, False], [True, False]) == 1.0
    assert balanced_accuracy([1, 0], [0, 1]) == 0.0
    # always predicting the majority class is 0.5, however imbalanced the data
    assert balanced_accuracy([1] * 9 + [0], [1] * 10) == 0.5


def test_balanced_accuracy_with_one_class_is_the_rate_of_that_class():
    assert balanced_accuracy([1, 1, 1, 1], [1, 0, 1, 1]) == 0.75  # TPR only
    assert balanced_accuracy([0, 0], [0, 1]) == 0.5  # TNR only
    assert balanced_accuracy([0, 0, 0], [1, 1, 1]) == 0.0


@pytest.mark.parametrize("labels, preds", [
    ([], []),  # empty
    ([1, 0], [1]),  # lengths differ
    ([1, 2], [1, 0]),  # not binary
    ([[1, 0]], [[1, 0]]),  # not 1-D
    (["1", "0"], [1, 0]),  # strings are not labels
])
def test_balanced_accuracy_rejects_bad_input(labels, preds):
    with pytest.raises(ValueError):
        balanced_accuracy(labels, preds)


# threshold -----------------------------------------------------------------------------------


def test_choose_threshold_separable_picks_the_gap_midpoint():
    t, ba = choose_threshold([0, 0, 1, 1], [0.1, 0.2, 0.7, 0.9])
    assert t == pytest.approx(0.45) and ba == 1.0


def test_choose_threshold_ties_go_to_the_candidate_closest_to_one_half():
    # unique scores 0.1 0.35 0.4 0.8 -> midpoints 0.225 (BA 0.75), 0.375 (0.5), 0.6 (0.75)
    t, ba = choose_threshold([0, 0, 1, 1], [0.1, 0.4, 0.35, 0.8])
    assert t == pytest.approx(0.6) and ba == pytest.approx(0.75)


def test_choose_threshold_equal_distance_tie_goes_to_the_lower():
    # unique 0.2 0.4 0.6 0.8 -> midpoints 0.3 (BA 0.75), 0.5 (0.5), 0.7 (0.75): 0.3 and 0.7 tie at 0.2
    t, ba = choose_threshold([0, 1, 0, 1], [0.2, 0.4, 0.6, 0.8])
    assert t == pytest.approx(0.3) and ba == pytest.approx(0.75)


def test_choose_threshold_without_a_midpoint_is_one_half():
    assert choose_threshold([0, 1, 1], [0.7, 0.7, 0.7]) == (0.5, 0.5)
    assert choose_threshold([1], [0.2]) == (0.5, 0.0)


def test_choose_threshold_one_class_maximises_that_class_rate():
    t, ba = choose_threshold([1, 1, 1], [0.2, 0.6, 0.9])  # midpoints 0.4, 0.75: 0.4 keeps 2 of 3
    assert t == pytest.approx(0.4) and ba == pytest.approx(2 / 3)


def test_choose_threshold_matches_brute_force_and_its_own_rule():
    rng = np.random.default_rng(1)
    for _ in range(20):
        y = rng.integers(0, 2, 60)
        s = np.round(rng.uniform(size=60) * 0.6 + 0.4 * y, 2)  # rounded: many duplicate scores
        t, ba = choose_threshold(y, s)
        assert balanced_accuracy(y, s >= t) == pytest.approx(ba)
        u = np.unique(s)
        best = max(balanced_accuracy(y, s >= m) for m in (u[:-1] + u[1:]) / 2)
        assert ba == pytest.approx(best)


def test_choose_threshold_between_adjacent_floats_reports_what_it_returns():
    a = 0.5
    b = np.nextafter(a, 1.0)  # the midpoint rounds onto one of the two
    t, ba = choose_threshold([0, 1], [a, b])
    assert balanced_accuracy([0, 1], np.array([a, b]) >= t) == ba


def test_choose_threshold_rejects_nan_scores():
    with pytest.raises(ValueError, match="finite"):
        choose_threshold([0, 1], [0.1, np.nan])


# calibration ---------------------------------------------------------------------------------


def test_ece_hand_computed():
    # bin 0: p .05, y 0 -> |0 - .05| * 1/4; bin 1: p .15 .15, y 1 0 -> |.5 - .15| * 2/4;
    # bin 9: p .95, y 1 -> |1 - .95| * 1/4.   .0125 + .175 + .0125 = .2
    assert expected_calibration_error([0, 1, 0, 1], [0.05, 0.15, 0.15, 0.95]) == pytest.approx(0.2)


def test_ece_perfect_calibration_and_single_bin():
    assert expected_calibration_error([1, 0, 0, 0], [0.25] * 4) == pytest.approx(0.0)
    # one bin: |mean(y) - mean(p)| = |0.5 - 0.6|
    assert expected_calibration_error([1, 0], [0.9, 0.3], n_bins=1) == pytest.approx(0.1)


def test_calibration_bin_edges():
    bins = calibration_bins([0, 1, 1, 0], [0.0, 0.1, 1.0, 0.999], n_bins=10)
    assert bins.counts.tolist() == [1, 1, 0, 0, 0, 0, 0, 0, 0, 2]  # 0.1 opens bin 1; 1.0 is in the last
    assert bins.accuracy[9] == 0.5 and bins.confidence[9] == pytest.approx(0.9995)
    assert np.isnan(bins.accuracy[5])  # empty bin
    np.testing.assert_allclose(bins.edges, np.linspace(0, 1, 11))


@pytest.mark.parametrize("probs", [[0.5, 1.2], [-0.1, 0.5], [0.5, np.inf]])
def test_ece_rejects_values_that_are_not_probabilities(probs):
    with pytest.raises(ValueError):
        expected_calibration_error([0, 1], probs)


def test_ece_rejects_bad_bins():
    with pytest.raises(ValueError):
        expected_calibration_error([0, 1], [0.2, 0.8], n_bins=0)


def test_reliability_diagram_writes_a_png(tmp_path):
    rng = np.random.default_rng(0)
    p = rng.uniform(size=200)
    y = (rng.uniform(size=200) < p).astype(int)
    out = reliability_diagram(y, p, tmp_path / "rel.png", title="random")
    data = (tmp_path / "rel.png").read_bytes()
    assert out == str(tmp_path / "rel.png")
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5_000
    # mostly empty bins are drawn too
    reliability_diagram([0, 1], [0.02, 0.97], tmp_path / "sparse.png", title="two samples")
    assert (tmp_path / "sparse.png").stat().st_size > 0
