"""A request's time budget, the same way in every firp HTTP API: the ``X-Request-Timeout`` header.

Why shared: the planner client gives each call a timeout; a service that keeps working on a call
after its client gave up wastes the capacity the next call needs. Both the scoring service and the
sim worker read the budget from this header (seconds), drop work whose budget ran out before it
started, and answer it ``504`` with rule ``deadline_exceeded``.
"""

from __future__ import annotations

import math

from firp.core.http_errors import ApiError

__all__ = ["MAX_TIMEOUT_S", "TIMEOUT_HEADER", "deadline_exceeded", "parse_timeout"]

TIMEOUT_HEADER = "X-Request-Timeout"
#: the longest budget a request may ask for (an hour): a larger one is a client's bug
MAX_TIMEOUT_S = 3600.0


def parse_timeout(value: str) -> float:
    """``X-Request-Timeout``: seconds, a positive finite number no larger than :data:`MAX_TIMEOUT_S`."""
    try:
        seconds = float(value)
    except ValueError:
        seconds = math.nan
    if not (math.isfinite(seconds) and 0.0 < seconds <= MAX_TIMEOUT_S):
        raise ApiError(400, TIMEOUT_HEADER, "timeout",
                       f"{TIMEOUT_HEADER} must be seconds in (0, {MAX_TIMEOUT_S:g}], got {value!r}")
    return seconds


def deadline_exceeded(stage: str, budget_s: float | None) -> ApiError:
    budget = f" of {budget_s:.3g} s" if budget_s is not None else ""
    return ApiError(504, None, "deadline_exceeded", f"the request's time budget{budget} ran out while it was {stage}")
