"""Comparing two runs' trial records: the same trials, whichever way they were run."""

from __future__ import annotations

import pytest

#: Floats the scoring service computed. Requests that reach the service together share one forward pass
#: (micro-batching), and a batch of another size may round the last bits of a score differently, so runs
#: whose trials overlap in time (parallel workers, Ray actors) agree on them to float precision, not bit for bit.
SCORE_FIELDS = ("scores", "candidate_scores")
SCORE_TOLERANCE = 2e-6


def comparable(record: dict) -> dict:
    """A trial record without what differs between any two runs (timings, request id) and without its scores."""
    return {k: v for k, v in record.items()
            if not k.endswith("_s") and k not in ("seconds", "request_id") + SCORE_FIELDS}


def assert_same_trials(got: list[dict], want: list[dict]) -> None:
    """Every field equal, scores to :data:`SCORE_TOLERANCE` (and the same candidates scored)."""
    assert [r["trial"] for r in got] == [r["trial"] for r in want]
    for g, w in zip(got, want):
        assert comparable(g) == comparable(w), g["trial"]
        assert ("scores" in g) == ("scores" in w)
        if "scores" in w:
            assert g["scores"] == pytest.approx(w["scores"], abs=SCORE_TOLERANCE), g["trial"]
        assert g.get("candidate_scores", {}).keys() == w.get("candidate_scores", {}).keys()
        assert list(g.get("candidate_scores", {}).values()) == pytest.approx(
            list(w.get("candidate_scores", {}).values()), abs=SCORE_TOLERANCE), g["trial"]
