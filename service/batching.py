"""Micro-batching: concurrent scoring requests share one forward pass through the ensemble.

Why: with the members fused (:mod:`firp.serving`), one plan of T = 120 costs ~8 ms and eight
plans ~14 ms (measured on this project's 2-core CPU, one torch thread), because the sequential
RSSM rollout is bound by per-step overhead and by streaming the weights, not by the number of
rows. So eight planners calling at once are served far sooner together than one after another.

How, and why this way:

* **No waiting window.** A request is never held back to wait for company: the runner takes
  whatever requests queued up while the previous pass ran (up to ``max_plans`` plans) and runs
  them together. A lone request goes straight through, so single-request latency is unchanged;
  under load the batches form by themselves.
* **One runner task** (started in the app's lifespan) owns the queue and hands each batch to
  the worker thread (:meth:`ServiceModel.score_jobs`, under the model's one inference token).
  The event loop stays free to parse the next requests while a batch runs.
* **Errors stay per request.** Each job is validated and its image decoded on its own; a bad plan
  fails its own request (422), never its batch neighbours'. An unexpected error in the shared
  pass fails the requests of that pass (500), and the runner goes on.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import anyio
import anyio.abc
from anyio.streams.memory import MemoryObjectReceiveStream, MemoryObjectSendStream

from service.errors import ServiceError
from service.metrics import ServiceMetrics
from service.scorer import ModelScores, ScoreJob, ServiceModel

__all__ = ["MicroBatcher"]

log = logging.getLogger("service")


@dataclass
class _Pending:
    job: ScoreJob
    done: anyio.Event = field(default_factory=anyio.Event)
    result: ModelScores | BaseException | None = None

    @property
    def n_plans(self) -> int:
        return len(self.job.plans)


class MicroBatcher:
    """Queue of scoring jobs served by one runner task (:meth:`run`) in shared forward passes."""

    def __init__(self, model: ServiceModel, max_plans: int, metrics: ServiceMetrics | None = None):
        if max_plans < 1:
            raise ValueError(f"max_plans must be >= 1, got {max_plans}")
        self.model = model
        self.max_plans = max_plans
        self.metrics = metrics
        self._send: MemoryObjectSendStream[_Pending]
        self._receive: MemoryObjectReceiveStream[_Pending]
        self._send, self._receive = anyio.create_memory_object_stream[_Pending](math.inf)
        self._carry: _Pending | None = None  # taken from the queue but did not fit the last batch
        self._running = False

    async def submit(self, job: ScoreJob) -> ModelScores:
        """Queue ``job`` and wait for its scores (or raise its error)."""
        if not self._running:
            raise ServiceError(503, None, "not_ready", "the service is not scoring (starting or stopping)",
                               headers={"Retry-After": "1"})
        pending = _Pending(job)
        self._send.send_nowait(pending)  # unbounded: the body limits and max_batch bound each job
        await pending.done.wait()
        if isinstance(pending.result, BaseException):
            raise pending.result
        assert pending.result is not None
        return pending.result

    async def _next_batch(self) -> list[_Pending]:
        first = self._carry if self._carry is not None else await self._receive.receive()
        self._carry = None
        batch, n = [first], first.n_plans
        while n < self.max_plans:
            try:
                item = self._receive.receive_nowait()
            except anyio.WouldBlock:
                break
            if n + item.n_plans > self.max_plans:
                self._carry = item  # first in the next batch: order is kept
                break
            batch.append(item)
            n += item.n_plans
        return batch

    async def run(self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
        """Serve the queue until cancelled; on the way out, fail what is still queued with a 503."""
        self._running = True
        task_status.started()
        batch: list[_Pending] = []
        try:
            while True:
                batch = await self._next_batch()
                jobs = [p.job for p in batch]
                try:
                    results: list[ModelScores | Exception] = await self.model.run(lambda: self.model.score_jobs(jobs))
                except Exception as exc:  # noqa: BLE001 - the pass failed: its requests get the error
                    log.exception("a scoring pass of %d requests failed", len(batch))
                    results = [exc] * len(batch)
                if self.metrics is not None:
                    self.metrics.micro_batch.observe(len(batch))
                for pending, result in zip(batch, results):
                    pending.result = result
                    pending.done.set()
                batch = []
        finally:
            self._running = False
            stopping = ServiceError(503, None, "not_ready", "the service is stopping", headers={"Retry-After": "1"})
            left = [p for p in batch if not p.done.is_set()]
            if self._carry is not None:
                left.append(self._carry)
            while True:
                try:
                    left.append(self._receive.receive_nowait())
                except (anyio.WouldBlock, anyio.EndOfStream, anyio.ClosedResourceError):
                    break
            for pending in left:
                pending.result = stopping
                pending.done.set()
