"""Which recorded episodes each exploration policy keeps, and the loop replayed on a scorer's scores (the
experiment end to end runs on the rounds' toy recording in test_learning_rounds.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from experiments.exploration_value import Evaluation, chosen_by_policy, policies, replay


def _record(seed: int, scores: dict[tuple, float], outcomes: dict[tuple, bool], deployed: tuple) -> dict:
    return {"task": "stacking", "seed": seed, "firp_order": list(deployed), "service_threshold": 0.5,
            "candidate_scores": {json.dumps(list(c)): s for c, s in scores.items()},
            "candidate_outcomes": {json.dumps(list(c)): o for c, o in outcomes.items()}}


A, B, C, D = ("a", "b"), ("b", "a"), ("c", "a"), ("d", "a")
RECORDS = [_record(7, {A: 0.9, B: 0.45, C: 0.1, D: 0.7}, {A: True, B: False, C: False, D: True}, deployed=A)]


def test_policies_keep_the_deployed_plan_and_add_the_least_sure_or_random_ones():
    assert policies([1, 2]) == ["deployed", "least-sure-1", "random-1", "least-sure-2", "random-2", "all"]
    scene = "stacking/7"
    assert chosen_by_policy(RECORDS, "deployed") == {(scene, A)}
    assert chosen_by_policy(RECORDS, "least-sure-1") == {(scene, A), (scene, B)}  # |0.45 - 0.5| is the least
    assert chosen_by_policy(RECORDS, "least-sure-2") == {(scene, A), (scene, B), (scene, D)}
    assert chosen_by_policy(RECORDS, "all") == {(scene, c) for c in (A, B, C, D)}
    drawn = chosen_by_policy(RECORDS, "random-2", seed=3)
    assert len(drawn) == 3 and (scene, A) in drawn  # as many labels as least-sure-2, the deployed one kept
    with pytest.raises(ValueError, match="unknown policy"):
        chosen_by_policy(RECORDS, "greedy-1")


def test_replay_walks_each_scene_in_the_planners_order():
    # scene x: candidates given out of order; the planner's first (index 0) fails, index 1 succeeds
    evaluation = Evaluation(scenes=["x", "x", "x", "y", "y"], order=np.array([2, 0, 1, 0, 1]),
                            labels=np.array([True, False, True, True, False]))
    scores = np.array([0.95, 0.2, 0.6, 0.3, 0.4])
    rules = replay(evaluation, scores, threshold=0.5)
    # x: index 0 (0.2) refused, index 1 (0.6) accepted -> success; ranking takes index 2 (0.95) -> success
    # y: nothing reaches 0.5 -> the last scored (index 1) fails; ranking takes index 1 (0.4) -> fails
    assert rules["threshold"].tolist() == [True, False]
    assert rules["rank"].tolist() == [True, False]
