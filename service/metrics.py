"""Prometheus metrics, one registry per app, and the middleware that measures every request.

Why a registry per app instead of prometheus_client's global one: tests (and a process embedding
two apps) create several apps; metrics registered globally twice raise, and would mix their counts.

What is measured, with the route *template* as label (``/v2/models/{name}/infer``, never the raw
path, so a scanner cannot blow up the label cardinality; unmatched paths are ``<unmatched>``, and
methods other than the usual seven are ``other``):

* ``firp_http_requests_total{route,method,status}`` and ``firp_http_request_duration_seconds``;
* ``firp_http_errors_total{route,status,rule}`` -- every error response by the rule it names;
* ``firp_inference_duration_seconds{endpoint}`` -- backbone + members only;
* ``firp_batch_plans{endpoint}`` -- plans per request;
* ``firp_micro_batch_requests`` -- requests per shared forward pass (micro-batching, see
  :mod:`service.batching`);
* ``firp_feature_cache_total{result}`` -- image feature cache hits and misses;
* ``firp_shed_requests_total{reason}`` -- scoring requests refused with 503 because the service
  was full (``concurrency``: admitted requests; ``queue``: plans waiting for a pass), and
  ``firp_deadline_exceeded_total{stage}`` -- requests answered 504 because their budget ran out
  (``queued``: dropped before any work; ``running``: the pass was under way), see
  :mod:`service.admission`; ``firp_admitted_requests`` and ``firp_queued_plans`` -- the two bounded
  quantities now;
* ``firp_event_loop_lag_seconds`` -- how late the event loop woke a task that slept 50 ms
  (:func:`watch_event_loop`): every request waits that long for its turn, whatever route;
* ``firp_ready``, ``firp_model_info{name,version,task}``, ``firp_model_informative`` and in-flight requests.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from starlette.routing import BaseRoute, Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.errors import SCOPE_RULE

__all__ = ["LOOP_PROBE_S", "MetricsMiddleware", "ServiceMetrics", "UNMATCHED", "watch_event_loop"]

UNMATCHED = "<unmatched>"

_LATENCY_BUCKETS = (0.001, 0.0025, 0.005, 0.0075, 0.01, 0.015, 0.02, 0.03, 0.04, 0.05, 0.075, 0.1, 0.15, 0.25, 0.5,
                    1.0, 2.5, 5.0, 10.0)
_BATCH_BUCKETS = (1, 2, 4, 8, 16, 32, 64, 128, 256)
_MICRO_BATCH_BUCKETS = (1, 2, 3, 4, 6, 8, 12, 16, 32, 64)
#: Methods kept as labels; any other (a client may send any token) is counted as "other".
_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})


#: the event loop's probe: sleep this long, and measure how much later than that it woke
LOOP_PROBE_S = 0.05


async def watch_event_loop(histogram: Histogram, period_s: float = LOOP_PROBE_S) -> None:
    """Forever: sleep ``period_s`` and record how late the loop woke up (its lag). Why: a request's
    latency inside the service starts when the loop first runs it; time spent before that (a loop busy
    parsing other requests' bodies, or waiting for the interpreter's lock) is seen only here."""
    import anyio

    while True:
        start = time.perf_counter()
        await anyio.sleep(period_s)
        histogram.observe(max(0.0, time.perf_counter() - start - period_s))


class ServiceMetrics:
    """The service's metrics in their own registry."""

    def __init__(self) -> None:
        r = self.registry = CollectorRegistry()
        self.requests = Counter("firp_http_requests", "HTTP requests by route template, method and status",
                                ["route", "method", "status"], registry=r)
        self.latency = Histogram("firp_http_request_duration_seconds", "HTTP request latency by route template",
                                 ["route", "method"], buckets=_LATENCY_BUCKETS, registry=r)
        self.errors = Counter("firp_http_errors", "Error responses by route template, status and rule",
                              ["route", "status", "rule"], registry=r)
        self.in_flight = Gauge("firp_http_requests_in_flight", "HTTP requests being handled", registry=r)
        self.inference = Histogram("firp_inference_duration_seconds", "Backbone + ensemble members per call",
                                   ["endpoint"], buckets=_LATENCY_BUCKETS, registry=r)
        self.batch_plans = Histogram("firp_batch_plans", "Plans scored per inference call", ["endpoint"],
                                     buckets=_BATCH_BUCKETS, registry=r)
        self.micro_batch = Histogram("firp_micro_batch_requests", "Requests scored together in one forward pass",
                                     buckets=_MICRO_BATCH_BUCKETS, registry=r)
        self.cache = Counter("firp_feature_cache", "Image feature cache lookups", ["result"], registry=r)
        self.shed = Counter("firp_shed_requests", "Scoring requests refused with 503 because the service was full",
                            ["reason"], registry=r)
        self.deadline_exceeded = Counter("firp_deadline_exceeded", "Scoring requests answered 504: budget ran out",
                                         ["stage"], registry=r)
        self.admitted = Gauge("firp_admitted_requests", "Scoring requests admitted and not yet answered", registry=r)
        self.queued_plans = Gauge("firp_queued_plans", "Plans waiting for a forward pass (micro-batching)",
                                  registry=r)
        self.loop_lag = Histogram("firp_event_loop_lag_seconds", "How late the event loop woke a task that slept "
                                  f"{LOOP_PROBE_S * 1000:g} ms", buckets=_LATENCY_BUCKETS, registry=r)
        self.ready = Gauge("firp_ready", "1 when the bundle is loaded and warmed up", registry=r)
        self.model_info = Gauge("firp_model_info", "The loaded bundle (value 1)", ["name", "version", "task"],
                                registry=r)
        self.model_informative = Gauge(
            "firp_model_informative", "1: the bundle's validation balanced accuracy interval lies above 0.5; "
            "0: it reaches 0.5 (clients execute TAMP's first plan); -1: the bundle carries no evidence", registry=r)

    def observe_inference(self, endpoint: str, seconds: float, n_plans: int, cache_hit: bool) -> None:
        self.inference.labels(endpoint).observe(seconds)
        self.batch_plans.labels(endpoint).observe(n_plans)
        self.cache.labels("hit" if cache_hit else "miss").inc()

    def render(self) -> tuple[bytes, str]:
        return generate_latest(self.registry), CONTENT_TYPE_LATEST


def _route_template(scope: Scope, routes: Sequence[BaseRoute]) -> str:
    route = scope.get("route")
    path = getattr(route, "path", None)
    if isinstance(path, str):
        return path
    # Not routed (refused by a middleware first, or no such path): the template it would have had.
    for candidate in routes:
        match, _ = candidate.matches(scope)
        if match != Match.NONE:
            return getattr(candidate, "path", UNMATCHED)
    return UNMATCHED


class MetricsMiddleware:
    """Pure ASGI (no BaseHTTPMiddleware: it would add a task and a copy per request)."""

    def __init__(self, app: ASGIApp, metrics: ServiceMetrics, routes: Sequence[BaseRoute] = ()):
        self.app = app
        self.metrics = metrics
        self.routes = tuple(routes)  # to label requests refused before routing (413, 415)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        status = 500
        start = time.perf_counter()

        async def send_wrapper(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
            await send(message)

        self.metrics.in_flight.inc()
        try:
            await self.app(scope, receive, send_wrapper)
        except BaseException:
            status = 500
            scope.setdefault(SCOPE_RULE, "internal")
            raise
        finally:
            self.metrics.in_flight.dec()
            route = _route_template(scope, self.routes)
            method = scope.get("method", "")
            method = method if method in _METHODS else "other"
            self.metrics.requests.labels(route, method, str(status)).inc()
            self.metrics.latency.labels(route, method).observe(time.perf_counter() - start)
            if status >= 400:
                self.metrics.errors.labels(route, str(status), scope.get(SCOPE_RULE, "unknown")).inc()
