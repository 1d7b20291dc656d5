"""What a planner's decisions on a bundle's scores may rest on, and the rules that make them.

A bundle carries its *decision evidence* in its manifest (``decision_evidence``, written by
``firp certify`` or by the export of a study): the ensemble's balanced accuracy at the bundle's threshold
on the validation episodes, with a stratified bootstrap confidence interval, and the scores of the
validation failures. Two uses:

* **Uninformative bundles do no harm.** When the interval reaches 0.5 the bundle is not shown to be better
  than a coin on held-out episodes; the service says so (``/v1/model``, readiness, a metric) and the
  planner client executes TAMP's first plan instead of replanning on its scores, so TAMP + FIRP cannot fall
  below TAMP alone by the scorer's doing.
* **A conformal acceptance rule.** Given ``n`` validation failures' scores and a new failed plan's score
  exchangeable with them, accepting only scores above the ``k``-th smallest, ``k = ceil((n + 1)(1 - alpha))``,
  accepts a failing plan with probability at most ``alpha`` (split conformal, class-conditional on failures).

The interval is computed at the bundle's own threshold, which was chosen on the same episodes: an
optimistic interval, so "uninformative" is a conservative verdict (a bundle marked so is certainly weak).

Torch-free: the planner client and the service both read it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = ["DECISION_RULES", "EVIDENCE_KEY", "balanced_accuracy_interval", "chosen_by_rule", "conformal_threshold",
           "decision_evidence", "first_accepted", "highest", "is_informative", "paired_comparison"]

EVIDENCE_KEY = "decision_evidence"  # the manifest's section
#: the client's rules: the paper's (first plan whose score reaches the bundle's threshold, else the last
#: scored), the ranking (the highest-scored of all candidates), the conformal one (the paper's rule at the
#: threshold that bounds the false-accept rate at alpha)
DECISION_RULES = ("threshold", "rank", "conformal")


def _balanced_accuracy(labels: np.ndarray, predictions: np.ndarray) -> np.ndarray:
    """Balanced accuracy along the last axis (rows of resamples): mean of the two classes' recalls."""
    pos = labels.sum(axis=-1)
    neg = labels.shape[-1] - pos
    tpr = (labels & predictions).sum(axis=-1) / pos
    tnr = (~labels & ~predictions).sum(axis=-1) / neg
    return (tpr + tnr) / 2.0


def balanced_accuracy_interval(labels: Sequence[bool] | np.ndarray, scores: Sequence[float] | np.ndarray,
                               threshold: float, *, resamples: int = 2000, level: float = 0.95,
                               seed: int = 0) -> tuple[float, float, float]:
    """(balanced accuracy, lower, upper) of ``scores >= threshold`` against ``labels``.

    Percentile bootstrap, stratified: each resample draws the successes and the failures separately with
    replacement, so every resample has both classes in the validation set's proportions."""
    y = np.asarray(labels, dtype=bool)
    s = np.asarray(scores, dtype=float)
    if y.shape != s.shape or y.ndim != 1:
        raise ValueError(f"labels {y.shape} and scores {s.shape} must be two vectors of one length")
    if y.all() or not y.any():
        raise ValueError("balanced accuracy needs successes and failures among the validation episodes")
    if not 0 < level < 1:
        raise ValueError(f"level must lie in (0, 1), got {level}")
    predictions = s >= threshold
    point = float(_balanced_accuracy(y, predictions))
    rng = np.random.default_rng(seed)
    pos, neg = np.flatnonzero(y), np.flatnonzero(~y)
    picks = np.concatenate([rng.choice(pos, (resamples, len(pos))), rng.choice(neg, (resamples, len(neg)))], axis=1)
    values = _balanced_accuracy(y[picks], predictions[picks])
    tail = (1.0 - level) / 2.0
    return point, float(np.quantile(values, tail)), float(np.quantile(values, 1.0 - tail))


def conformal_threshold(failure_scores: Sequence[float] | np.ndarray, alpha: float) -> float:
    """The smallest threshold ``q`` such that accepting ``score >= q`` accepts a failing plan with
    probability at most ``alpha`` (``inf`` when there are too few failures to bound it: nothing accepted)."""
    if not 0 < alpha < 1:
        raise ValueError(f"alpha is a probability and must lie in (0, 1), got {alpha}")
    s = np.sort(np.asarray(failure_scores, dtype=float))
    k = math.ceil((len(s) + 1) * (1.0 - alpha))
    if k > len(s):
        return math.inf
    return float(np.nextafter(s[k - 1], np.inf))  # strictly above the k-th smallest failure's score


def decision_evidence(labels: Sequence[bool] | np.ndarray, scores: Sequence[float] | np.ndarray, threshold: float,
                      *, resamples: int = 2000, level: float = 0.95, seed: int = 0) -> dict:
    """The manifest's ``decision_evidence`` section for validation ``labels`` and ensemble ``scores``."""
    y = np.asarray(labels, dtype=bool)
    s = np.asarray(scores, dtype=float)
    point, low, high = balanced_accuracy_interval(y, s, threshold, resamples=resamples, level=level, seed=seed)
    return {
        "balanced_accuracy": point,
        "interval": [low, high],
        "level": level,
        "resamples": resamples,
        "method": "stratified percentile bootstrap over the validation episodes, at the bundle's threshold",
        "informative": low > 0.5,
        "n_successes": int(y.sum()),
        "n_failures": int((~y).sum()),
        # what the conformal rule needs: the validation failures' ensemble scores, sorted
        "failure_scores": sorted(float(v) for v in s[~y]),
    }


def is_informative(evidence: dict | None) -> bool | None:
    """True or False from a bundle's evidence; None when the bundle carries none (nothing is known)."""
    if not evidence or "interval" not in evidence:
        return None
    return bool(evidence["interval"][0] > 0.5)


def first_accepted(scores: Sequence[float], threshold: float) -> tuple[int, bool]:
    """The paper's rule on plans scored in the planner's order: the first whose score reaches the threshold
    (and True), else the last one scored (and False: the budget ran out)."""
    if len(scores) == 0:
        raise ValueError("no scored plan to choose from")
    for index, score in enumerate(scores):
        if score >= threshold:
            return index, True
    return len(scores) - 1, False


def highest(scores: Sequence[float]) -> int:
    """The ranking rule: the highest-scored plan (the planner's earlier candidate on a tie)."""
    if len(scores) == 0:
        raise ValueError("no scored plan to choose from")
    return int(np.argmax(np.asarray(scores, dtype=float)))


def chosen_by_rule(rule: str, scores: Sequence[float], threshold: float, conformal: float | None = None
                   ) -> tuple[int, bool]:
    """(index, accepted) of the plan ``rule`` executes among ``scores`` (the planner's order).

    ``accepted`` says whether the plan cleared the rule's bar: the threshold for the paper's rule, the conformal
    threshold for the conformal one; the ranking executes its pick in any case and "accepts" it when its score
    reaches the bundle's threshold."""
    if rule == "threshold":
        return first_accepted(scores, threshold)
    if rule == "rank":
        index = highest(scores)
        return index, scores[index] >= threshold
    if rule == "conformal":
        if conformal is None:
            raise ValueError("the conformal rule needs the bundle's failure scores (decision_evidence)")
        return first_accepted(scores, conformal)
    raise ValueError(f"unknown decision rule {rule!r}; one of {DECISION_RULES}")


def paired_comparison(labels: Sequence[bool] | np.ndarray, groups: Sequence[str], *, new_scores: Sequence[float],
                      new_threshold: float, current_scores: Sequence[float], current_threshold: float,
                      resamples: int = 2000, level: float = 0.95, seed: int = 0) -> dict:
    """Two bundles on the same held-out episodes: each one's balanced accuracy at its own threshold, the
    difference (new - current) and its interval.

    Paired and clustered: each resample draws whole scenes (``groups``: a scene's candidates share their
    image and their physics, so they are not independent) with replacement and scores both bundles on the
    same draw, so what the two have in common cancels out of the difference. Resamples that lack a class
    are drawn again (they have no balanced accuracy)."""
    y = np.asarray(labels, dtype=bool)
    new, current = np.asarray(new_scores, dtype=float), np.asarray(current_scores, dtype=float)
    if not (y.shape == new.shape == current.shape == (len(groups),)) or y.ndim != 1:
        raise ValueError("labels, groups and both bundles' scores must be vectors of one length")
    if y.all() or not y.any():
        raise ValueError("the held-out episodes need successes and failures")
    new_pred, current_pred = new >= new_threshold, current >= current_threshold
    point_new, point_current = float(_balanced_accuracy(y, new_pred)), float(_balanced_accuracy(y, current_pred))
    names, members = np.unique(np.asarray(groups), return_inverse=True)
    by_group = [np.flatnonzero(members == g) for g in range(len(names))]
    rng = np.random.default_rng(seed)
    deltas: list[float] = []
    while len(deltas) < resamples:
        pick = np.concatenate([by_group[g] for g in rng.integers(0, len(by_group), len(by_group))])
        yy = y[pick]
        if yy.all() or not yy.any():
            continue
        deltas.append(float(_balanced_accuracy(yy, new_pred[pick]) - _balanced_accuracy(yy, current_pred[pick])))
    tail = (1.0 - level) / 2.0
    return {"new_balanced_accuracy": point_new, "current_balanced_accuracy": point_current,
            "difference": point_new - point_current,
            "interval": [float(np.quantile(deltas, tail)), float(np.quantile(deltas, 1.0 - tail))],
            "level": level, "resamples": resamples, "n_episodes": int(len(y)), "n_scenes": int(len(names)),
            "n_successes": int(y.sum()), "n_failures": int((~y).sum()),
            "method": "paired percentile bootstrap over held-out scenes, each bundle at its own threshold"}
