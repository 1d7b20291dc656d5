"""The statistics decisions on a bundle's scores rest on (firp.core.decisions): the bootstrap interval of
the validation balanced accuracy, the conformal threshold, and the rules' picks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from firp.core.decisions import (balanced_accuracy_interval, chosen_by_rule, conformal_threshold, decision_evidence,
                                 first_accepted, highest, is_informative)


def test_a_perfect_scorer_has_a_degenerate_interval_at_one_and_is_informative():
    labels = np.array([True] * 30 + [False] * 20)
    scores = np.where(labels, 0.9, 0.1)
    point, low, high = balanced_accuracy_interval(labels, scores, 0.5, resamples=500)
    assert point == low == high == 1.0
    evidence = decision_evidence(labels, scores, 0.5, resamples=500)
    assert evidence["informative"] and is_informative(evidence) is True
    assert evidence["failure_scores"] == [0.1] * 20 and (evidence["n_successes"], evidence["n_failures"]) == (30, 20)


def test_a_coin_on_few_episodes_is_uninformative_and_the_interval_holds_its_point():
    rng = np.random.default_rng(3)
    labels = np.array([True] * 21 + [False] * 15)  # about the replacement bundle's 72 halved
    scores = rng.uniform(size=labels.size)
    point, low, high = balanced_accuracy_interval(labels, scores, 0.5, resamples=2000)
    assert low < point < high and low <= 0.5 <= high
    assert is_informative(decision_evidence(labels, scores, 0.5)) is False


def test_the_interval_narrows_with_more_episodes_and_is_reproducible():
    rng = np.random.default_rng(0)
    def case(n):
        labels = rng.uniform(size=n) < 0.5
        scores = np.clip(labels * 0.3 + rng.normal(0.35, 0.2, n), 0, 1)
        return balanced_accuracy_interval(labels, scores, 0.5, seed=1)
    small, large = case(60), case(2000)
    assert large[2] - large[1] < (small[2] - small[1]) / 3
    labels = np.arange(40) % 2 == 0
    scores = np.linspace(0, 1, 40)
    assert balanced_accuracy_interval(labels, scores, 0.5, seed=7) == balanced_accuracy_interval(labels, scores, 0.5,
                                                                                                 seed=7)


def test_conformal_threshold_bounds_the_rate_of_accepted_failures():
    """Over many draws of a validation set and fresh failures from the same distribution, the rate at which
    a fresh failure clears the threshold stays at most alpha (and near it: the bound is not vacuous)."""
    rng = np.random.default_rng(0)
    alpha, rates = 0.1, []
    for _ in range(400):
        q = conformal_threshold(rng.beta(2, 5, size=59), alpha)
        rates.append(np.mean(rng.beta(2, 5, size=500) >= q))
    assert 0.07 < np.mean(rates) <= alpha + 0.005


def test_conformal_threshold_edge_cases_and_errors():
    assert conformal_threshold([0.1, 0.2, 0.3], 0.1) == math.inf  # 3 failures cannot bound 10%: accept nothing
    q = conformal_threshold([0.3, 0.1, 0.2, 0.4], 0.25)  # k = ceil(5 * 0.75) = 4: just above the largest
    assert q > 0.4 and q == np.nextafter(0.4, 1)
    for bad in (0.0, 1.0, -0.1):
        with pytest.raises(ValueError, match="alpha"):
            conformal_threshold([0.1], bad)
    with pytest.raises(ValueError, match="successes and failures"):
        balanced_accuracy_interval([True, True], [0.9, 0.8], 0.5)
    assert is_informative(None) is None and is_informative({}) is None


def test_the_rules_pick_as_documented():
    scores = [0.2, 0.7, 0.1, 0.95]
    assert first_accepted(scores, 0.6) == (1, True) and first_accepted(scores, 0.99) == (3, False)
    assert highest(scores) == 3 and highest([0.5, 0.5]) == 0  # a tie goes to the planner's earlier candidate
    assert chosen_by_rule("threshold", scores, 0.6) == (1, True)
    assert chosen_by_rule("rank", scores, 0.6) == (3, True) and chosen_by_rule("rank", scores, 0.99) == (3, False)
    assert chosen_by_rule("conformal", scores, 0.6, conformal=0.15) == (0, True)
    with pytest.raises(ValueError, match="failure scores"):
        chosen_by_rule("conformal", scores, 0.6)
    with pytest.raises(ValueError, match="unknown decision rule"):
        chosen_by_rule("best", scores, 0.6)
