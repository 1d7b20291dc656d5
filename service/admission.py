"""Admission control: bounded work and a time budget per request, so overload is refused, not queued.

Why: a scoring pass costs milliseconds, but a queue that grows without bound turns a burst into
seconds of latency for everyone, and work a client has already given up on is still computed
(measured before this module: 64 clients posting batches of 16 plans saw p50 2.6 s). A service
that is boring to operate refuses early and cheaply instead:

* **Concurrency.** At most ``max_concurrent_requests`` scoring requests are admitted at a time;
  one more is answered ``503`` (rule ``overloaded``) with ``Retry-After`` at once, before its body
  is read. Health, readiness and metrics routes are never counted or shed.
* **Queued work.** The micro-batcher (:mod:`service.batching`) holds at most ``max_queued_plans``
  plans waiting for a pass, and no more than ``max_queue_wait_s`` of work by the measured cost of a
  plan; a request that would exceed either gets the same ``503`` -- before its body is read when
  the queue is already over a bound, so a refusal costs microseconds, not a JSON parse.
* **Deadlines.** Each scoring request has a budget: the ``X-Request-Timeout`` header (seconds), the
  V2 ``parameters.timeout`` (microseconds, as Triton's schedule-policy extension) or the
  ``request_timeout_s`` setting, the tightest of them, counted from the request's arrival. Work
  whose budget runs out while it waits for a pass is dropped, never computed, and answered ``504``
  (rule ``deadline_exceeded``); a pass already running finishes, but its request is answered ``504``
  when its budget ends.

Both refusals use the one error shape and are counted (``firp_shed_requests_total{reason}``,
``firp_deadline_exceeded_total{stage}``), so an operator sees load shedding on a dashboard, not in
clients' complaints.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Protocol

from fastapi import Request
from starlette.datastructures import Headers
from starlette.routing import BaseRoute, Match
from starlette.types import ASGIApp, Receive, Scope, Send

from firp.core.deadlines import MAX_TIMEOUT_S, TIMEOUT_HEADER, deadline_exceeded, parse_timeout
from service.errors import ServiceError, error_response
from service.metrics import ServiceMetrics

__all__ = ["Admission", "AdmissionControl", "InFlight", "MAX_TIMEOUT_S", "SCOPE_DEADLINE", "TIMEOUT_HEADER", "deadline_exceeded",
           "deadline_of", "overloaded", "release_reservation", "remaining", "tighten_deadline"]

#: the request's deadline (``time.monotonic()`` seconds, or None: no budget), in the ASGI scope
SCOPE_DEADLINE = "firp.deadline"
#: when the request arrived (``time.monotonic()``), in the ASGI scope
SCOPE_ARRIVAL = "firp.arrival"
#: the callable that releases the request's reservation in the micro-batcher's bounds, until it is released
SCOPE_RESERVATION = "firp.reservation"


def release_reservation(scope: Scope) -> None:
    """Release the request's reservation (:meth:`service.batching.MicroBatcher.admit`), once: when its job
    is submitted (then it counts as queued plans), or when the request ends without one."""
    release = scope.pop(SCOPE_RESERVATION, None)
    if release is not None:
        release()


def overloaded(message: str, retry_after_s: int) -> ServiceError:
    return ServiceError(503, None, "overloaded", message, headers={"Retry-After": str(retry_after_s)})


def deadline_of(request: Request) -> float | None:
    return request.scope.get(SCOPE_DEADLINE)


def remaining(deadline: float | None) -> float | None:
    """Seconds left before ``deadline`` (may be negative), or None without one."""
    return None if deadline is None else deadline - time.monotonic()


def tighten_deadline(request: Request, budget_s: float) -> None:
    """Make the request's deadline at most ``budget_s`` after its arrival (a V2 ``parameters.timeout``)."""
    arrival = request.scope.get(SCOPE_ARRIVAL, time.monotonic())
    current = request.scope.get(SCOPE_DEADLINE)
    candidate = arrival + budget_s
    request.scope[SCOPE_DEADLINE] = candidate if current is None else min(current, candidate)


class InFlight:
    """How many scoring requests are admitted and not yet answered (read by the drain on SIGTERM)."""

    def __init__(self, metrics: ServiceMetrics):
        self.count = 0
        self.metrics = metrics

    def add(self, n: int) -> None:
        self.count += n
        self.metrics.admitted.set(self.count)


class Admission(Protocol):
    """What admission asks of a queue (:class:`service.batching.MicroBatcher`)."""

    def admit(self) -> str | None: ...

    def release(self) -> None: ...


class AdmissionControl:
    """Pure ASGI middleware on the scoring routes: the concurrency bound and each request's deadline."""

    def __init__(self, app: ASGIApp, *, routes: Sequence[BaseRoute], max_concurrent: int, default_timeout_s: float,
                 retry_after_s: int, metrics: ServiceMetrics, in_flight: InFlight,
                 queue: Callable[[], Admission | None] = lambda: None):
        self.app = app
        self.routes = tuple(routes)
        self.max_concurrent = max_concurrent
        self.default_timeout_s = default_timeout_s
        self.retry_after_s = retry_after_s
        self.metrics = metrics
        self.in_flight = in_flight
        self.queue = queue  # the micro-batcher's admission (None: no queue to bound)

    def _scoring(self, scope: Scope) -> bool:
        return any(route.matches(scope)[0] == Match.FULL for route in self.routes)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not self._scoring(scope):
            await self.app(scope, receive, send)
            return
        arrival = time.monotonic()
        header = Headers(scope=scope).get(TIMEOUT_HEADER)
        try:
            budget = parse_timeout(header) if header is not None else self.default_timeout_s or None
        except ServiceError as exc:
            await error_response(scope, exc.status, exc.field, exc.rule, exc.message)(scope, receive, send)
            return
        scope[SCOPE_ARRIVAL] = arrival
        scope[SCOPE_DEADLINE] = None if budget is None else arrival + budget
        if self.in_flight.count >= self.max_concurrent:
            self.metrics.shed.labels("concurrency").inc()
            exc = overloaded(f"{self.in_flight.count} scoring requests are being served, the most this service takes "
                             "at once (setting max_concurrent_requests); retry later", self.retry_after_s)
            await error_response(scope, exc.status, exc.field, exc.rule, exc.message, exc.headers)(scope, receive, send)
            return
        queue = self.queue()
        full = None if queue is None else queue.admit()
        if full is not None:  # refused before the body is read or parsed: the cheapest answer there is
            self.metrics.shed.labels("queue").inc()
            exc = overloaded(full, self.retry_after_s)
            await error_response(scope, exc.status, exc.field, exc.rule, exc.message, exc.headers)(scope, receive, send)
            return
        if queue is not None:
            scope[SCOPE_RESERVATION] = queue.release
        self.in_flight.add(1)
        try:
            await self.app(scope, receive, send)
        finally:
            self.in_flight.add(-1)
            release_reservation(scope)  # a request that ended before its submit (an error, a 422)
