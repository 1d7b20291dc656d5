"""Per-model inference statistics in the shape of the Open Inference Protocol's statistics extension
(Triton's ``GET /v2/models/{name}/stats``), so the tools that read Triton's numbers read these.

Counted per loaded bundle (a hot swap starts a new count with the new version): requests answered
(``success``) or failed (``fail``) with their total time, the time requests waited for a pass
(``queue``), the passes' compute time (``compute_infer``; one pass may serve several requests), the
plans scored (``inference_count``) and the passes run (``execution_count``). Times are nanoseconds,
as the extension specifies. Prometheus (``/metrics``) carries the same story as histograms; this is
the protocol's view of it.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

__all__ = ["InferenceStatistics"]


@dataclass
class _Duration:
    count: int = 0
    ns: int = 0

    def add(self, seconds: float, count: int = 1) -> None:
        self.count += count
        self.ns += int(seconds * 1e9)

    def as_dict(self) -> dict[str, int]:
        return {"count": self.count, "ns": self.ns}


@dataclass
class InferenceStatistics:
    """Counters of one bundle; updated from the event loop and the worker thread (hence the lock)."""

    success: _Duration = field(default_factory=_Duration)
    fail: _Duration = field(default_factory=_Duration)
    queue: _Duration = field(default_factory=_Duration)
    compute_infer: _Duration = field(default_factory=_Duration)
    inference_count: int = 0  # plans scored
    execution_count: int = 0  # forward passes
    last_inference_ms: int = 0  # milliseconds since the epoch
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def answered(self, seconds: float, plans: int) -> None:
        with self._lock:
            self.success.add(seconds)
            self.inference_count += plans
            self.last_inference_ms = int(time.time() * 1000)

    def failed(self, seconds: float) -> None:
        with self._lock:
            self.fail.add(seconds)

    def waited(self, seconds: float) -> None:
        with self._lock:
            self.queue.add(seconds)

    def computed(self, seconds: float, requests: int) -> None:
        with self._lock:
            self.compute_infer.add(seconds, requests)
            self.execution_count += 1

    def as_dict(self, name: str, version: str) -> dict:
        with self._lock:
            zero = {"count": 0, "ns": 0}
            return {"name": name, "version": version, "last_inference": self.last_inference_ms,
                    "inference_count": self.inference_count, "execution_count": self.execution_count,
                    "inference_stats": {"success": self.success.as_dict(), "fail": self.fail.as_dict(),
                                        "queue": self.queue.as_dict(), "compute_input": zero,
                                        "compute_infer": self.compute_infer.as_dict(), "compute_output": zero},
                    "batch_stats": []}
