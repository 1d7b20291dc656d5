"""Micro-batching: concurrent scoring requests share one forward pass through the ensemble.

Why: with the members fused (:mod:`firp.serving`), one plan of T = 120 costs ~8 ms and eight
plans ~14 ms (measured on this project's 2-core CPU, one torch thread), because the sequential
RSSM rollout is bound by per-step overhead and by streaming the weights, not by the number of
rows. So eight planners calling at once are served far sooner together than one after another.

How, and why this way:

* **No waiting window.** A request is never held back to wait for company: the scoring thread takes
  whatever requests queued up while the previous pass ran (up to ``max_plans`` plans) and runs
  them together. A lone request goes straight through, so single-request latency is unchanged;
  under load the batches form by themselves.
* **One scoring thread** (started by :meth:`MicroBatcher.run` in the app's lifespan) takes each
  batch from the queue and scores it (:meth:`ServiceModel.score_jobs`), then takes the next one at
  once: the event loop only queues jobs and hands back answers. Why a thread of its own rather than
  a pass per ``to_thread`` call from a task on the event loop: under load the loop is busy parsing
  request bodies, and a pass handed over by the loop waited for the loop after every pass -- the
  scoring thread sat idle 41% of the time under 64 clients (py-spy), while requests queued.
* **Bounded, with deadlines** (:mod:`service.admission`). At most ``max_queued_plans`` plans wait
  for a pass: a request beyond that is refused with 503 at once. A request whose deadline passes
  while it waits is answered 504 and dropped when the scoring thread reaches it, so no pass computes work
  nobody waits for.
* **Admitted work counts before it is queued.** Between its admission and its submit a request's
  body is read and parsed on the event loop. A burst admitted whole because the queue was empty
  when it arrived would be parsed whole (~10 ms per batch of 16 plans, the event loop's time) and
  then mostly refused: slow refusals and slow probes. So admission (:meth:`admit`) reserves the
  plans a request is expected to bring (a moving average of what requests brought) and the bounds
  count the reservations too; a request's submit turns its reservation into queued plans.
* **Errors stay per request.** Each job is validated and its image decoded on its own; a bad plan
  fails its own request (422), never its batch neighbours'. An unexpected error in the shared
  pass fails the requests of that pass (500), and the scoring thread goes on.
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import anyio
import anyio.abc
import anyio.to_thread

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
    """Queue of scoring jobs served by one scoring thread (started by :meth:`run`) in shared passes."""

    def __init__(self, model: ServiceModel, max_plans: int, metrics: ServiceMetrics | None = None,
                 max_queued_plans: int | None = None, retry_after_s: int = 1, max_queue_wait_s: float = 0.0):
        if max_plans < 1:
            raise ValueError(f"max_plans must be >= 1, got {max_plans}")
        self.model = model  # read once per pass: a hot swap assigns the next one here
        self.max_plans = max_plans
        self.metrics = metrics
        self.max_queued_plans = max_queued_plans
        self.retry_after_s = retry_after_s
        self.queued_plans = 0  # plans submitted and not yet taken by the scoring thread
        self.reserved = 0  # requests admitted (reserved) and not yet submitted: their bodies are being parsed
        self.plans_per_request = 1.0  # what a request brings: moving average over the submitted ones
        self.max_queue_wait_s = max_queue_wait_s  # 0: no bound on the expected wait
        self.seconds_per_plan: float | None = None  # measured: moving average over the last passes
        self._lock = threading.Lock()  # the queue and queued_plans, shared by the event loop and the thread
        self._work = threading.Condition(self._lock)  # notified on a new job, and to stop
        self._queue: deque[_Pending] = deque()
        self._stopping = False
        self._running = False
        self._loop: asyncio.AbstractEventLoop | None = None

    @property
    def waiting(self) -> int:
        """Jobs queued and not yet taken into a pass."""
        with self._lock:
            return len(self._queue)

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
        with self._work:
            self._queue.append(pending)
            self._set_queued(self.queued_plans + n)
            job.timeline.queued_ns = time.time_ns()
            self._work.notify()
        with anyio.move_on_after(math.inf if deadline is None else deadline - now):
            await pending.done.wait()
        if not pending.done.is_set():  # the budget ran out first
            with self._lock:  # the thread takes a job under the lock: taken or dropped, never both
                stage = "running" if pending.taken else "queued"
                pending.abandoned = True  # the thread drops it if it has not taken it yet
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

    # ------------------------------------------------------------- the scoring thread

    def _answer(self, items: list[_Pending]) -> None:
        """Wake the requests of ``items`` (their ``result`` set) on the event loop."""
        if not items or self._loop is None:
            return
        try:
            self._loop.call_soon_threadsafe(lambda: [item.done.set() for item in items])
        except RuntimeError:  # the loop is closed: nobody waits any more
            pass

    def _next_batch(self) -> list[_Pending] | None:
        """The next pass's jobs in queue order (None: stopping). Jobs whose deadline passed while they
        waited are answered 504 and dropped, never computed. Called on the scoring thread."""
        with self._work:
            while True:
                while not self._queue and not self._stopping:
                    self._work.wait()
                if self._stopping:
                    return None
                batch: list[_Pending] = []
                expired: list[_Pending] = []
                n, now = 0, time.monotonic()
                while self._queue:
                    item = self._queue[0]
                    if batch and n + item.n_plans > self.max_plans:
                        break  # first in the next pass: order is kept
                    self._queue.popleft()
                    self._set_queued(self.queued_plans - item.n_plans)
                    if item.expired(now):
                        if not item.abandoned:  # its waiter has not noticed yet: answer it from here
                            self._count_deadline("queued")
                            item.result = deadline_exceeded("queued", item.budget_s)
                            expired.append(item)
                        continue
                    item.taken = True
                    item.job.timeline.taken_ns = time.time_ns()
                    batch.append(item)
                    n += item.n_plans
                self._answer(expired)
                if batch:
                    return batch

    def _serve(self) -> None:
        """The scoring thread: pass after pass until stopped."""
        while (batch := self._next_batch()) is not None:
            model = self.model  # read once: a hot swap never splits a pass between two bundles
            started = time.perf_counter()
            for pending in batch:
                model.statistics.waited(started - pending.queued_at)
            try:
                results: list[ModelScores | Exception] = model.score_jobs([p.job for p in batch])
            except Exception as exc:  # noqa: BLE001 - the pass failed: its requests get the error
                log.exception("a scoring pass of %d requests failed", len(batch))
                results = [exc] * len(batch)
            elapsed = time.perf_counter() - started
            self._observe_pass(elapsed, sum(p.n_plans for p in batch))
            model.statistics.computed(elapsed, len(batch))
            if self.metrics is not None:
                self.metrics.micro_batch.observe(len(batch))
            for pending, result in zip(batch, results):
                pending.result = result
            self._answer(batch)

    async def run(self, *, task_status: anyio.abc.TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
        """Start the scoring thread and serve until cancelled; on the way out, let the pass in progress
        finish, then fail what is still queued with a 503."""
        self._loop = asyncio.get_running_loop()
        self._stopping = False
        thread = threading.Thread(target=self._serve, name="scoring", daemon=True)
        thread.start()
        self._running = True
        task_status.started()
        try:
            await anyio.sleep_forever()
        finally:
            self._running = False
            with self._work:
                self._stopping = True
                self._work.notify_all()
            with anyio.CancelScope(shield=True):
                await anyio.to_thread.run_sync(thread.join)
            stopping = ServiceError(503, None, "not_ready", "the service is stopping", headers={"Retry-After": "1"})
            with self._lock:
                left = list(self._queue)
                self._queue.clear()
                self._set_queued(0)
            for pending in left:
                pending.result = stopping
                pending.done.set()
