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
* **Bounded, with deadlines** (:mod:`service.admission`). At most ``max_queued_plans`` plans wait
  for a pass: a request beyond that is refused with 503 at once. A request whose deadline passes
  while it waits is answered 504 and dropped when the runner reaches it, so no pass computes work
  nobody waits for.
* **Admitted work counts before it is queued.** Between its admission and its submit a request's
  body is read and parsed on the event loop. A burst admitted whole because the queue was empty
  when it arrived would be parsed whole (~10 ms per batch of 16 plans, the event loop's time) and
  then mostly refused: slow refusals and slow probes. So admission (:meth:`admit`) reserves the
  plans a request is expected to bring (a moving average of what requests brought) and the bounds
  count the reservations too; a request's submit turns its reservation into queued plans.
* **Errors stay per request.** Each job is validated and its image decoded on its own; a bad plan
  fails its own request (422), never its batch neighbours'. An unexpected error in the shared
  pass fails the requests of that pass (500), and the runner goes on.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import anyio
import anyio.abc
from anyio.streams.memory import MemoryObjectReceiveStream, MemoryObjectSendStream

from service.admission import deadline_exceeded, overloaded
from service.errors import ServiceError
from service.metrics import ServiceMetrics
from service.scorer import ModelScores, ScoreJob, ServiceModel

__all__ = ["MicroBatcher"]

log = logging.getLogger("service")


@dataclass
class _Pending:
    job: ScoreJob
    deadline: float | None = None  # time.monotonic() seconds
    budget_s: float | None = None  # for the 504's message
    queued_at: float = field(default_factory=time.perf_counter)
    done: anyio.Event = field(default_factory=anyio.Event)
    result: ModelScores | BaseException | None = None
    taken: bool = False  # in a pass (computed, or being computed)
    abandoned: bool = False  # its request was answered (504) before a pass took it

    def expired(self, now: float) -> bool:
        return self.abandoned or (self.deadline is not None and now >= self.deadline)

    @property
    def n_plans(self) -> int:
        return len(self.job.plans)


class MicroBatcher:
    """Queue of scoring jobs served by one runner task (:meth:`run`) in shared forward passes."""

    def __init__(self, model: ServiceModel, max_plans: int, metrics: ServiceMetrics | None = None,
                 max_queued_plans: int | None = None, retry_after_s: int = 1, max_queue_wait_s: float = 0.0):
        if max_plans < 1:
            raise ValueError(f"max_plans must be >= 1, got {max_plans}")
        self.model = model
        self.max_plans = max_plans
        self.metrics = metrics
        self.max_queued_plans = max_queued_plans
        self.retry_after_s = retry_after_s
        self.queued_plans = 0  # plans submitted and not yet taken by the runner
        self.reserved = 0  # requests admitted (reserved) and not yet submitted: their bodies are being parsed
        self.plans_per_request = 1.0  # what a request brings: moving average over the submitted ones
        self.max_queue_wait_s = max_queue_wait_s  # 0: no bound on the expected wait
        self.seconds_per_plan: float | None = None  # measured: moving average over the last passes
        self._send: MemoryObjectSendStream[_Pending]
        self._receive: MemoryObjectReceiveStream[_Pending]
        self._send, self._receive = anyio.create_memory_object_stream[_Pending](math.inf)
        self._carry: _Pending | None = None  # taken from the queue but did not fit the last batch
        self._running = False

    async def submit(self, job: ScoreJob, deadline: float | None = None) -> ModelScores:
        """Queue ``job`` and wait for its scores (or raise its error): 503 if the queue is full, 504 if
        ``deadline`` (``time.monotonic()`` seconds) passes first."""
        if not self._running:
            raise ServiceError(503, None, "not_ready", "the service is not scoring (starting or stopping)",
                               headers={"Retry-After": "1"})
        n = len(job.plans)
        self.plans_per_request = 0.8 * self.plans_per_request + 0.2 * n
        reason = self.full(n)
        if reason is not None:
            self._count_shed()
            raise overloaded(f"this request brings {n} plans, and {reason}", self.retry_after_s)
        now = time.monotonic()
        pending = _Pending(job, deadline, None if deadline is None else deadline - now)
        if pending.expired(now):
            self._count_deadline("queued")
            raise deadline_exceeded("queued", pending.budget_s)
        self._set_queued(self.queued_plans + n)
        job.timeline.queued_ns = time.time_ns()
        self._send.send_nowait(pending)  # bounded by max_queued_plans, above
        with anyio.move_on_after(math.inf if deadline is None else deadline - now):
            await pending.done.wait()
        if not pending.done.is_set():  # the budget ran out first
            stage = "running" if pending.taken else "queued"
            pending.abandoned = True  # the runner drops it if it has not taken it yet
            self._count_deadline(stage)
            raise deadline_exceeded(stage, pending.budget_s)
        if isinstance(pending.result, BaseException):
            raise pending.result
        assert pending.result is not None
        return pending.result

    def _observe_pass(self, seconds: float, plans: int) -> None:
        per_plan = seconds / max(plans, 1)
        previous = self.seconds_per_plan
        self.seconds_per_plan = per_plan if previous is None else 0.8 * previous + 0.2 * per_plan

    @property
    def reserved_plans(self) -> int:
        """The plans the admitted, not yet submitted requests are expected to bring."""
        return round(self.reserved * self.plans_per_request)

    def expected_wait_s(self, extra_plans: int = 0) -> float:
        """How long ``extra_plans`` more would wait for their pass (behind the queued and the reserved
        plans), from the measured cost of a plan."""
        return (self.queued_plans + self.reserved_plans + extra_plans) * (self.seconds_per_plan or 0.0)

    def full(self, extra_plans: int = 0) -> str | None:
        """Why ``extra_plans`` more cannot be queued now (None: they can). A request always may when
        nothing waits or is reserved, however large: a lone request is never refused."""
        if self.queued_plans == 0 and self.reserved == 0:
            return None
        waiting = f"{self.queued_plans} plans are waiting for a pass and {self.reserved} requests are being read"
        n = self.queued_plans + self.reserved_plans + extra_plans
        if self.max_queued_plans is not None and n > self.max_queued_plans:
            return (f"{waiting}; the most that may wait is {self.max_queued_plans} plans (setting max_queued_plans); "
                    "retry later")
        wait = self.expected_wait_s(extra_plans)
        if self.max_queue_wait_s and wait > self.max_queue_wait_s:
            return (f"{waiting}, about {wait:.2f} s of work; the longest wait allowed is {self.max_queue_wait_s:g} s "
                    "(setting max_queue_wait_s); retry later")
        return None

    def admit(self) -> str | None:
        """Admission of a request whose body is not read yet: why not (None: admitted, and the plans it
        is expected to bring are reserved until :meth:`release`)."""
        reason = self.full(max(1, round(self.plans_per_request)))
        if reason is None:
            self.reserved += 1
        return reason

    def release(self) -> None:
        """An admitted request submitted its job (now queued plans) or ended without one."""
        self.reserved -= 1

    def _set_queued(self, n: int) -> None:
        self.queued_plans = n
        if self.metrics is not None:
            self.metrics.queued_plans.set(n)

    def _count_shed(self) -> None:
        if self.metrics is not None:
            self.metrics.shed.labels("queue").inc()

    def _count_deadline(self, stage: str) -> None:
        if self.metrics is not None:
            self.metrics.deadline_exceeded.labels(stage).inc()

    def _take(self, item: _Pending) -> _Pending:
        self._set_queued(self.queued_plans - item.n_plans)
        return item

    def _live(self, item: _Pending, now: float) -> bool:
        """False (and the request answered) for a job whose deadline passed while it was queued."""
        if not item.expired(now):
            return True
        if not item.abandoned:  # its waiter has not noticed yet: answer it from here
            self._count_deadline("queued")
            item.result = deadline_exceeded("queued", item.budget_s)
            item.done.set()
        return False

    async def _next_batch(self) -> list[_Pending]:
        """The next pass's jobs, in queue order; jobs whose deadline passed are answered and skipped."""
        while True:
            first = self._carry if self._carry is not None else self._take(await self._receive.receive())
            self._carry = None
            if self._live(first, time.monotonic()):
                break
        first.taken = True
        first.job.timeline.taken_ns = time.time_ns()
        batch, n = [first], first.n_plans
        while n < self.max_plans:
            try:
                item = self._take(self._receive.receive_nowait())
            except anyio.WouldBlock:
                break
            if not self._live(item, time.monotonic()):
                continue
            if n + item.n_plans > self.max_plans:
                self._carry = item  # first in the next batch: order is kept
                break
            item.taken = True
            item.job.timeline.taken_ns = time.time_ns()
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
                model = self.model  # read once: a hot swap never splits a pass between two bundles
                started = time.perf_counter()
                for pending in batch:
                    model.statistics.waited(started - pending.queued_at)
                try:
                    results: list[ModelScores | Exception] = await model.run(lambda: model.score_jobs(jobs))
                except Exception as exc:  # noqa: BLE001 - the pass failed: its requests get the error
                    log.exception("a scoring pass of %d requests failed", len(batch))
                    results = [exc] * len(batch)
                self._observe_pass(time.perf_counter() - started, sum(p.n_plans for p in batch))
                model.statistics.computed(time.perf_counter() - started, len(batch))
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
