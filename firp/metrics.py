"""Evaluation metrics of a success classifier: balanced accuracy, threshold choice, calibration.

numpy only (matplotlib is imported inside :func:`reliability_diagram` alone), so the service and
the training tools can share these definitions without pulling torch or a plotting stack.

Why these metrics: the paper reports *balanced accuracy* (the mean of the true-positive and the
true-negative rate) because success/failure datasets are imbalanced and plain accuracy rewards
always guessing the majority class. The decision threshold is chosen on validation data to
maximise that same number, and is shipped with the model. The ensemble's probability is also
shown to people and used for replanning, so its calibration (ECE, reliability diagram) is measured
too.

Conventions used throughout: ``labels`` are 1 = success (positive), 0 = failure; a score or a
probability ``p`` predicts success iff ``p >= threshold``.
"""

from __future__ import annotations

import os
from typing import NamedTuple

import numpy as np

__all__ = [
    "CalibrationBins",
    "balanced_accuracy",
    "calibration_bins",
    "choose_threshold",
    "expected_calibration_error",
    "reliability_diagram",
]


def _binary(name: str, values: object) -> np.ndarray:
    """``values`` as a 1-D bool array; anything but 0/1 (or True/False) is an error, not a cast."""
    arr = np.asarray(values)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {arr.shape}")
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"{name} must be numeric 0/1, got dtype {arr.dtype}")
    if not np.isin(arr, (0, 1)).all():
        raise ValueError(f"{name} must contain only 0 and 1")
    return arr.astype(bool)


def _finite(name: str, values: object) -> np.ndarray:
    arr = np.asarray(values)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {arr.shape}")
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"{name} must be numeric, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite (no NaN or infinity)")
    return arr


def _same_nonempty(labels: np.ndarray, other: np.ndarray, other_name: str) -> None:
    if len(labels) != len(other):
        raise ValueError(f"labels and {other_name} differ in length: {len(labels)} != {len(other)}")
    if len(labels) == 0:
        raise ValueError("no samples: the metric is undefined on empty input")


def balanced_accuracy(labels: object, predictions: object) -> float:
    """Mean of the true-positive rate (recall on successes) and true-negative rate (on failures).

    Degenerate case, defined on purpose: when ``labels`` hold only **one** class, the rate of the
    missing class is 0/0. It is left out and the result is the rate of the class that is present,
    i.e. the plain accuracy (as scikit-learn does, minus its warning). A small validation split with
    one class then still gets a meaningful number (and :func:`choose_threshold` still works) instead
    of a NaN that would silently poison every comparison. Empty input raises ``ValueError``.
    """
    y = _binary("labels", labels)
    p = _binary("predictions", predictions)
    _same_nonempty(y, p, "predictions")
    rates = []
    if y.any():
        rates.append(float(np.mean(p[y])))  # TPR
    if (~y).any():
        rates.append(float(np.mean(~p[~y])))  # TNR
    return float(np.mean(rates))


def choose_threshold(labels: object, scores: object) -> tuple[float, float]:
    """The threshold that maximises balanced accuracy of ``scores >= threshold`` on ``labels``.

    Candidates are the midpoints between consecutive sorted unique scores: every distinct split of
    the validation set is reached exactly once, and a midpoint leaves a margin on both sides for
    test scores near the boundary. Among equally good candidates the one closest to 0.5 wins (for
    probabilities, the least surprising choice; exact ties at equal distance go to the lower one).
    With fewer than two distinct scores there is no midpoint and the threshold is 0.5.

    Returns ``(threshold, balanced accuracy at that threshold)``. O(n log n).
    """
    y = _binary("labels", labels)
    s = _finite("scores", scores)
    _same_nonempty(y, s, "scores")
    unique = np.unique(s)
    if len(unique) < 2:
        return 0.5, balanced_accuracy(y, s >= 0.5)
    candidates = (unique[:-1] + unique[1:]) / 2.0
    # Predicted positive iff score >= t: count, per candidate, positives/negatives at or above it.
    # Counting against the candidate itself (not against the next unique score) keeps the result
    # exact even when a midpoint of two adjacent floats rounds onto one of them.
    pos = np.sort(s[y])
    neg = np.sort(s[~y])
    rates = []
    if len(pos):
        rates.append((len(pos) - np.searchsorted(pos, candidates, side="left")) / len(pos))  # TPR
    if len(neg):
        rates.append(np.searchsorted(neg, candidates, side="left") / len(neg))  # TNR
    bacc = np.mean(rates, axis=0)
    best = bacc.max()
    tied = np.flatnonzero(bacc >= best - 1e-12)
    dist = np.abs(candidates[tied] - 0.5)
    pick = tied[np.flatnonzero(dist == dist.min())[0]]  # candidates are sorted: the first is the lower
    return float(candidates[pick]), float(bacc[pick])


class CalibrationBins(NamedTuple):
    """Per-bin statistics of equal-width probability bins over [0, 1] (empty bins: count 0, NaN)."""

    edges: np.ndarray  # (n_bins + 1,)
    counts: np.ndarray  # (n_bins,) int
    confidence: np.ndarray  # (n_bins,) mean predicted success probability in the bin
    accuracy: np.ndarray  # (n_bins,) observed success frequency in the bin


def calibration_bins(labels: object, probs: object, n_bins: int = 10) -> CalibrationBins:
    """Bin the predicted success probabilities into ``n_bins`` equal-width bins.

    Bin ``b`` holds ``b/n <= p < (b+1)/n``; the last bin also holds ``p = 1``. Calibration is that
    of the *success probability* itself (the positive class), not of ``max(p, 1-p)``: the number
    the service reports is P(success), and "0.8" should mean "8 in 10 such plans succeed".
    """
    y = _binary("labels", labels)
    p = _finite("probs", probs)
    _same_nonempty(y, p, "probs")
    if not isinstance(n_bins, (int, np.integer)) or n_bins < 1:
        raise ValueError(f"n_bins must be a positive integer, got {n_bins!r}")
    if (p < 0).any() or (p > 1).any():
        raise ValueError("probs must lie in [0, 1]")
    idx = np.minimum((p * n_bins).astype(np.int64), n_bins - 1)
    counts = np.bincount(idx, minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        confidence = np.bincount(idx, weights=p, minlength=n_bins) / counts
        accuracy = np.bincount(idx, weights=y.astype(np.float64), minlength=n_bins) / counts
    return CalibrationBins(np.linspace(0.0, 1.0, n_bins + 1), counts, confidence, accuracy)


def expected_calibration_error(labels: object, probs: object, n_bins: int = 10) -> float:
    """ECE = sum over bins of ``(n_b / n) * |observed success frequency - mean probability|``.

    Equal-width bins (see :func:`calibration_bins`), weighted by their share of the samples, so
    empty bins contribute nothing. 0 is perfect calibration; the value depends on ``n_bins``, which
    is why manifests record it next to the number.
    """
    bins = calibration_bins(labels, probs, n_bins)
    full = bins.counts > 0
    weights = bins.counts[full] / bins.counts.sum()
    return float(np.sum(weights * np.abs(bins.accuracy[full] - bins.confidence[full])))


def reliability_diagram(
    labels: object, probs: object, path: str | os.PathLike, title: str = "Reliability", n_bins: int = 10
) -> str:
    """Write a PNG: per-bin observed success frequency vs mean predicted probability, the diagonal
    of perfect calibration, and below it a histogram of how many samples fall in each bin (a bin
    of three samples far from the diagonal means little; the histogram shows that).

    Uses matplotlib's Agg canvas directly (no pyplot): no global figure state and no display
    backend, so it is safe in a server process and in threads. Returns ``path`` as a string.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    bins = calibration_bins(labels, probs, n_bins)
    ece = expected_calibration_error(labels, probs, n_bins)
    width = 1.0 / n_bins
    centres = bins.edges[:-1] + width / 2
    full = bins.counts > 0

    fig = Figure(figsize=(5, 6.5))
    FigureCanvasAgg(fig)
    top, bottom = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    top.plot([0, 1], [0, 1], linestyle="--", color="grey", label="perfect calibration")
    top.bar(centres[full], bins.accuracy[full], width=width * 0.9, color="tab:blue", alpha=0.35,
            edgecolor="tab:blue", label="observed success frequency")
    top.plot(bins.confidence[full], bins.accuracy[full], marker="o", color="tab:blue", label="bin (mean p, frequency)")
    top.set_xlim(0, 1)
    top.set_ylim(0, 1)
    top.set_ylabel("observed success frequency")
    top.set_title(f"{title}\nECE = {ece:.3f} ({n_bins} bins, n = {int(bins.counts.sum())})")
    top.legend(loc="upper left", fontsize="small")
    bottom.bar(centres, bins.counts, width=width * 0.9, color="tab:grey")
    bottom.set_xlabel("predicted success probability")
    bottom.set_ylabel("count")
    fig.tight_layout()
    out = os.fspath(path)
    fig.savefig(out, format="png", dpi=100)
    return out
