"""Scoring plans with a loaded bundle: the ensemble scorer the service runs, and its fused FIRP path.

Face of the package: :class:`EnsembleScorer` and :class:`EnsembleResult` (:mod:`firp.serving.scorer`).
"""

from firp.serving.scorer import EnsembleResult, EnsembleScorer, Strategy

__all__ = ["EnsembleResult", "EnsembleScorer", "Strategy"]
