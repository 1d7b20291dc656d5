"""OpenTelemetry tracing for every firp HTTP part: off by default, on through the standard ``OTEL_*`` variables.

Why: a planner's trial calls the scoring service several times and the sim worker twice or more;
request ids (:mod:`firp.core.request_log`) find a trial's log lines, but not where its time went.
With tracing on, one trace holds the whole trial: the planner's ``trial`` span, its HTTP calls (W3C
``traceparent`` propagated by OpenTelemetry's httpx instrumentation), each service's server span
(its FastAPI instrumentation), and inside them the spans that matter for latency -- the scoring
service's ``queue wait``, ``backbone`` and ``ensemble pass``, the sim worker's ``world queue wait``
and ``execute``.

Switched on by the variables every OpenTelemetry SDK reads, nothing of firp's own:

* ``OTEL_TRACES_EXPORTER`` -- ``otlp`` (OTLP over HTTP, ``OTEL_EXPORTER_OTLP_ENDPOINT`` /
  ``OTEL_EXPORTER_OTLP_TRACES_ENDPOINT``, default ``http://localhost:4318``), ``console`` (spans as
  JSON on standard output), several comma-separated, or ``none``. Unset, tracing stays off unless an
  OTLP endpoint is set (then ``otlp``): the specification's default exporter is ``otlp``, but a
  process that sends spans nobody asked for to a port nobody listens on is not a sane default here.
* ``OTEL_SDK_DISABLED=true`` turns it off whatever else is set.
* ``OTEL_SERVICE_NAME`` / ``OTEL_RESOURCE_ATTRIBUTES`` name the process (default: the part's name,
  ``firp-service``, ``firp-sim-worker``, ``firp-robosuite-worker``, ``firp-planner``);
  ``OTEL_TRACES_SAMPLER`` / ``OTEL_TRACES_SAMPLER_ARG`` sample; ``OTEL_BSP_*`` tune the batch span
  processor; ``OTEL_PROPAGATORS`` picks the propagation format (default W3C trace context + baggage).
  The SDK reads these itself.

Off, nothing is instrumented and nothing of OpenTelemetry's SDK is imported, so tracing costs
nothing when it is not used. A span recorded after the fact (:func:`record_span`) carries the
timestamps the work measured on its own thread, so the worker threads need no tracing context.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the SDK is imported only when tracing is on
    from opentelemetry.sdk.trace import TracerProvider
    from opentelemetry.trace import Tracer

__all__ = ["TracingConfigError", "configure_tracing", "exporter_names", "instrument_app", "instrument_client",
           "record_span", "span", "tracer_of", "tracing_requested", "use_tracer_provider"]

_TRUE = {"true", "1", "yes", "on"}
_lock = threading.Lock()
_provider: TracerProvider | None = None


class TracingConfigError(ValueError):
    """An ``OTEL_*`` variable asks for something this install cannot do; the message names the variable."""


def exporter_names(environ: Mapping[str, str] | None = None) -> list[str]:
    """The span exporters the environment asks for (empty: tracing off)."""
    env = os.environ if environ is None else environ
    if env.get("OTEL_SDK_DISABLED", "").strip().lower() in _TRUE:
        return []
    given = env.get("OTEL_TRACES_EXPORTER")
    if given is None:
        endpoint = env.get("OTEL_EXPORTER_OTLP_TRACES_ENDPOINT") or env.get("OTEL_EXPORTER_OTLP_ENDPOINT")
        return ["otlp"] if endpoint else []
    names = [n.strip().lower() for n in given.split(",") if n.strip()]
    return [] if names in ([], ["none"]) else [n for n in names if n != "none"]


def tracing_requested(environ: Mapping[str, str] | None = None) -> bool:
    return bool(exporter_names(environ))


def _exporter(name: str) -> Any:
    if name == "console":
        from opentelemetry.sdk.trace.export import ConsoleSpanExporter

        return ConsoleSpanExporter()
    if name == "otlp":
        protocol = os.environ.get("OTEL_EXPORTER_OTLP_TRACES_PROTOCOL") or os.environ.get("OTEL_EXPORTER_OTLP_PROTOCOL")
        if protocol not in (None, "", "http/protobuf"):
            raise TracingConfigError(f"OTEL_EXPORTER_OTLP_PROTOCOL={protocol!r}: this install exports OTLP over "
                                     "http/protobuf only")
        from opentelemetry.exporter.otlp.proto.http.trace_exporter import OTLPSpanExporter

        return OTLPSpanExporter()
    raise TracingConfigError(f"OTEL_TRACES_EXPORTER names {name!r}; this install knows otlp, console and none")


def configure_tracing(service_name: str, environ: Mapping[str, str] | None = None) -> TracerProvider | None:
    """The process's tracer provider as the ``OTEL_*`` variables ask (None: tracing off). Made once per
    process and reused: a second app in the same process (tests) shares it."""
    global _provider
    if _provider is not None:
        return _provider
    names = exporter_names(environ)
    if not names:
        return None
    with _lock:
        if _provider is not None:
            return _provider
        from opentelemetry import trace
        from opentelemetry.sdk.resources import SERVICE_NAME, Resource
        from opentelemetry.sdk.trace import TracerProvider
        from opentelemetry.sdk.trace.export import BatchSpanProcessor

        env = os.environ if environ is None else environ
        named = "OTEL_SERVICE_NAME" in env or "service.name=" in env.get("OTEL_RESOURCE_ATTRIBUTES", "")
        # Resource.create merges OTEL_SERVICE_NAME / OTEL_RESOURCE_ATTRIBUTES; ours only fills a gap
        provider = TracerProvider(resource=Resource.create({} if named else {SERVICE_NAME: service_name}))
        for name in names:
            provider.add_span_processor(BatchSpanProcessor(_exporter(name)))
        trace.set_tracer_provider(provider)
        _provider = provider
        return provider


def use_tracer_provider(provider: TracerProvider | None) -> None:
    """Hand this process's parts a tracer provider made elsewhere (an application embedding firp, a
    test with an in-memory exporter): :func:`configure_tracing` returns it from now on, whatever the
    ``OTEL_*`` variables say. None forgets it."""
    global _provider
    with _lock:
        _provider = provider


def tracer_of(provider: TracerProvider | None, name: str) -> Tracer | None:
    return None if provider is None else provider.get_tracer(name)


def instrument_app(app: Any, provider: TracerProvider) -> None:
    """Server spans for every route of a FastAPI ``app``, continuing the caller's trace (``traceparent``).
    Health, readiness and metrics probes are left out: they would drown the traces that matter."""
    from opentelemetry.instrumentation.fastapi import FastAPIInstrumentor

    FastAPIInstrumentor.instrument_app(app, tracer_provider=provider, exclude_spans=["receive", "send"],
                                       excluded_urls="healthz,readyz,metrics,v2/health")


def instrument_client(client: Any, provider: TracerProvider) -> None:
    """Client spans for an ``httpx.Client``'s calls, and the current trace context sent with each."""
    from opentelemetry.instrumentation.httpx import HTTPXClientInstrumentor

    HTTPXClientInstrumentor.instrument_client(client, tracer_provider=provider)


def record_span(tracer: Tracer | None, name: str, start_ns: int, end_ns: int,
                attributes: Mapping[str, Any] | None = None, error: str | None = None) -> None:
    """A finished span under the current context, from timestamps (``time.time_ns()``) measured
    elsewhere -- on a worker thread, or across a queue. No-op without a tracer."""
    if tracer is None:
        return
    from opentelemetry.trace import Status, StatusCode

    span = tracer.start_span(name, start_time=start_ns, attributes=dict(attributes or {}))
    if error is not None:
        span.set_status(Status(StatusCode.ERROR, error))
    span.end(end_time=max(end_ns, start_ns))


@contextmanager
def span(tracer: Tracer | None, name: str, attributes: Mapping[str, Any] | None = None) -> Iterator[str | None]:
    """A span around the block, current inside it (calls made inside are its children); yields its
    trace id as 32 hex digits, or None without a tracer."""
    if tracer is None:
        yield None
        return
    with tracer.start_as_current_span(name, attributes=dict(attributes or {})) as current:
        yield format(current.get_span_context().trace_id, "032x")
