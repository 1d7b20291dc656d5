"""The FastAPI app: lifespan (load, verify, warm up the bundle), health, and the /v1 scoring routes.

Why the bundle is loaded in the lifespan and not lazily: a service that starts with a missing,
corrupt or incompatible bundle must fail at start-up with the file and the rule named
(:class:`firp.bundle.BundleError`), not answer its first request with a 500. Readiness (``/readyz``)
turns true only after a warm-up inference, so a load balancer never routes a planner's first call
to a cold model.

Layout of a request: :class:`~firp.core.request_log.RequestLog` (outermost: the request id, the
request's log line) -> :class:`~service.metrics.MetricsMiddleware` (counts everything, also refusals) -> :class:`~service.admission.AdmissionControl` (scoring routes: 503 when full,
the request's deadline) -> :class:`~service.guard.RequestGuard` (415/413 before any parsing) -> FastAPI
(request bodies parsed by pydantic-core, :mod:`service.routing`; pydantic validation; 422s converted
to the one error shape by :mod:`service.errors`) -> route -> :func:`service.deps.score_off_loop` ->
the micro-batcher (:mod:`service.batching`, a task of the lifespan) -> worker thread, one forward
pass at a time, shared by the requests that queued while the previous one ran.
"""

from __future__ import annotations

import gc
import logging
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING, Any

import anyio.to_thread
from fastapi import APIRouter, Depends, FastAPI, Request
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel

from firp.bundle import BundleError
from firp.core.request_log import RequestLog
from firp.core.tracing import configure_tracing, instrument_app, tracer_of
from service.deps import (
    check_batch_size,
    check_task,
    image_digest,
    ready_model,
    require_api_key,
    score_off_loop,
    settings_of,
)
from service.admission import AdmissionControl, InFlight
from service.batching import MicroBatcher
from service.errors import error_responses, install_error_handlers
from service.guard import RequestGuard
from service.images import ImageLimits, decode_base64_image
from service.metrics import MetricsMiddleware, ServiceMetrics, watch_event_loop
from service.routing import FastJSONRoute
from service.schemas import (
    BatchScoreRequest,
    BatchScoreResponse,
    HealthResponse,
    ModelInfo,
    ModelRef,
    PlanResult,
    ReadyResponse,
    ScoreRequest,
    ScoreResponse,
)
from service.scorer import ModelScores, ServiceModel, set_torch_threads
from service.settings import ServiceSettings
from service.repository import ModelRepository
from service.v2 import V2InferRoute, v2_router
from service.v2.repository import repository_router

if TYPE_CHECKING:
    from opentelemetry.sdk.trace import TracerProvider

__all__ = ["StartupError", "create_app"]

log = logging.getLogger("service")

API_TITLE = "FIRP plan scoring service"
API_VERSION = "1.0.0"


class StartupError(RuntimeError):
    """The service cannot start: the message says which bundle and why."""


_POST_ERRORS = error_responses(400, 401, 413, 415, 422, 503, 504)
_GET_ERRORS = error_responses(401, 503)


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    settings: ServiceSettings = app.state.settings
    metrics: ServiceMetrics = app.state.metrics
    set_torch_threads(settings.threads)
    path = settings.bundle_dir
    log.info("loading bundle %s", path)
    try:
        model = await anyio.to_thread.run_sync(ServiceModel.load, path, settings.feature_cache_size,
                                                     settings.device)
    except BundleError as exc:
        log.error("cannot start: %s", exc)
        raise StartupError(f"cannot load the bundle at {path}: {exc}") from exc
    if settings.task is not None and settings.task != model.task:
        raise StartupError(f"the bundle at {path} is for task {model.task!r}, but task {settings.task!r} was asked for")
    warmup_ms = await anyio.to_thread.run_sync(model.warm_up)
    freeze_startup_objects()
    async with anyio.create_task_group() as tasks:
        tasks.start_soon(watch_event_loop, metrics.loop_lag)
        if settings.micro_batch:
            batcher = MicroBatcher(model, settings.micro_batch_max_plans, metrics,
                                   max_queued_plans=settings.max_queued_plans, retry_after_s=settings.retry_after_s,
                                   max_queue_wait_s=settings.max_queue_wait_s)
            await tasks.start(batcher.run)
            app.state.batcher = batcher
        app.state.phase = "ready"
        app.state.repository.install(model, path)
        log.info("ready: bundle %s version %s (task %s, %d members, T in [%d, %d]), warm-up %.0f ms, "
                 "micro-batching %s", model.name, model.version, model.task, model.n_members, model.t_min,
                 model.t_max, warmup_ms, "on" if settings.micro_batch else "off")
        try:
            yield
        finally:
            app.state.phase = "stopping"
            metrics.ready.set(0)
            tasks.cancel_scope.cancel()  # the batcher answers what is still queued with a 503


def freeze_startup_objects() -> None:
    """Move every object alive after start-up (modules, the bundle's tensors and modules, the warm-up's
    caches) out of the garbage collector's sight (``gc.freeze``).

    Why: a full collection walks every tracked object. After start-up that is hundreds of thousands of
    objects that live as long as the process, and under load (each batch of plans parses into
    thousands of lists) full collections came every second and held the interpreter -- the event
    loop included -- for up to 220 ms: measured with 64 clients, 22 full collections in 25 s, 3.2 s
    in all, and a /readyz p99 of 190 ms. Frozen, they walk only what requests allocated (0.3 s in
    all), /readyz stays within 25 ms and the same load scores 25% more plans per second
    (``benchmarks/service_overload.py``). A bundle swapped out later is freed by reference counting
    alone -- frozen objects are never collected as cycles, and a test checks that a dropped model
    leaves none -- and the bundle swapped in stays unfrozen: one bundle's worth of objects."""
    gc.collect()
    gc.freeze()


def _model_ref(model: ServiceModel, scores: ModelScores | None = None) -> ModelRef:
    """The bundle that scored (``scores``), which a hot swap may have made another than the route's ``model``."""
    if scores is not None and scores.version:
        return ModelRef(name=scores.name, version=scores.version)
    return ModelRef(name=model.name, version=model.version)


def _plan_result(scores: ModelScores, i: int) -> dict[str, object]:
    return {
        "score": float(scores.probabilities[i]),
        "success": bool(scores.success[i]),
        "member_scores": scores.member_probabilities[i].tolist(),
        "spread": float(scores.spread[i]),
        "failure_step": scores.failure_steps[i],
    }


def _json(body: BaseModel) -> Response:
    """A response model serialised by pydantic-core directly: FastAPI would validate the model it was
    just built from again and encode it with ``json.dumps`` (~0.2 ms more per request on the event
    loop, measured). ``response_model`` on the route still documents the schema."""
    return Response(body.model_dump_json(), media_type="application/json")


def _guarded(settings: ServiceSettings) -> list[Any]:
    """The API key dependency, only when a key is configured: so the OpenAPI schema says whether
    the routes need X-API-Key, truthfully."""
    return [Depends(require_api_key)] if settings.api_key is not None else []


def _v1_router(guarded: list[Any]) -> APIRouter:
    router = APIRouter(prefix="/v1", tags=["scoring"], dependencies=guarded, route_class=FastJSONRoute)

    async def run(request: Request, endpoint: str, image: str, task: str | None, plans: list[Any],
                  fields: list[str]) -> tuple[ServiceModel, ModelScores]:
        """Both routes: ready model, task check, then image + plans scored off the event loop."""
        model = ready_model(request)
        check_task(task, model)
        limits = ImageLimits.from_settings(settings_of(request))
        key = image_digest(b"b64", image.encode("utf-8", "surrogatepass"))
        scores = await score_off_loop(request, model, endpoint, key, lambda: decode_base64_image(image, limits),
                                      plans, fields)
        return model, scores

    @router.post("/score", response_model=ScoreResponse, responses=_POST_ERRORS,
                 summary="Score one plan for one initial image")
    async def score(body: ScoreRequest, request: Request) -> Response:
        start = time.perf_counter()
        model, scores = await run(request, "/v1/score", body.image, body.task, [body.plan], ["plan"])
        attention = scores.attention[0]
        return _json(ScoreResponse(
            **_plan_result(scores, 0),
            threshold=scores.threshold,
            attention=None if attention is None else attention.tolist(),
            model=_model_ref(model, scores),
            request_id=body.request_id,
            elapsed_ms=(time.perf_counter() - start) * 1000.0,
        ))

    @router.post("/score/batch", response_model=BatchScoreResponse, responses=_POST_ERRORS,
                 summary="Score N candidate plans for one initial image in one call")
    async def score_batch(body: BatchScoreRequest, request: Request) -> Response:
        start = time.perf_counter()
        check_batch_size(len(body.plans), settings_of(request).max_batch, "plans")
        fields = [f"plans[{i}]" for i in range(len(body.plans))]
        model, scores = await run(request, "/v1/score/batch", body.image, body.task, body.plans, fields)
        return _json(BatchScoreResponse(
            results=[PlanResult(**_plan_result(scores, i)) for i in range(len(body.plans))],
            threshold=scores.threshold,
            model=_model_ref(model, scores),
            request_id=body.request_id,
            elapsed_ms=(time.perf_counter() - start) * 1000.0,
        ))

    @router.get("/model", response_model=ModelInfo, responses=_GET_ERRORS,
                summary="The loaded bundle: version, members, metrics, training data, contract, image size")
    async def model_info(request: Request) -> ModelInfo:
        return ModelInfo(**ready_model(request).manifest_summary())

    return router


def _health_router() -> APIRouter:
    router = APIRouter(tags=["operations"])

    @router.get("/healthz", response_model=HealthResponse, summary="The process is alive")
    async def healthz() -> HealthResponse:
        return HealthResponse()

    @router.get("/readyz", response_model=ReadyResponse,
                responses={503: {"model": ReadyResponse, "description": "starting or stopping"}},
                summary="The bundle is loaded and warmed up (200) or not (503)")
    async def readyz(request: Request) -> Response:
        state = request.app.state
        if state.phase != "ready":
            return JSONResponse(ReadyResponse(status=state.phase).model_dump(), status_code=503)
        return JSONResponse(ReadyResponse(status="ready", model=_model_ref(state.model), warmup_ms=state.model.warmup_ms,
                                          informative=state.model.informative).model_dump())

    @router.get("/metrics", response_class=Response, summary="Prometheus metrics (text exposition format)",
                responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}}})
    async def metrics(request: Request) -> Response:
        body, content_type = request.app.state.metrics.render()
        return Response(body, media_type=content_type)

    return router


def create_app(settings: ServiceSettings | None = None, tracer_provider: TracerProvider | None = None) -> FastAPI:
    """Build the app. Nothing is loaded until the lifespan starts (uvicorn, TestClient, ...).

    Tracing (:mod:`firp.core.tracing`) is on when ``tracer_provider`` is given, or when the ``OTEL_*``
    variables ask for it; off, nothing is instrumented."""
    settings = settings if settings is not None else ServiceSettings()
    if tracer_provider is None:
        tracer_provider = configure_tracing("firp-service")
    app = FastAPI(
        title=API_TITLE,
        version=API_VERSION,
        description=(
            "Scores how likely a robot action plan is to succeed, before it is executed, with an ensemble bundle "
            "of FIRP models. Every error is {\"error\": {\"field\", \"rule\", \"message\"}}."
        ),
        lifespan=_lifespan,
    )
    app.state.settings = settings
    app.state.metrics = ServiceMetrics()
    app.state.in_flight = InFlight(app.state.metrics)
    app.state.model = None
    app.state.batcher = None
    app.state.phase = "starting"
    app.state.repository = ModelRepository(app)
    app.state.tracer = tracer_of(tracer_provider, "firp.service")
    install_error_handlers(app)
    routers = [_health_router(), _v1_router(_guarded(settings)), v2_router(_guarded(settings)),
               repository_router(_guarded(settings))]
    for router in routers:
        app.include_router(router)
    # add_middleware wraps: the last added runs first.
    routes = [r for router in routers for r in router.routes]
    binary_routes = [r for r in routes if isinstance(r, V2InferRoute)]  # the binary tensor extension's routes
    optional_body = [r for r in routes if getattr(r, "path", "").startswith("/v2/repository")]
    app.add_middleware(RequestGuard, max_body_bytes=settings.max_body_bytes, routes=routes, binary_routes=binary_routes,
                       optional_body_routes=optional_body)
    # before the guard reads a body: an overloaded service refuses a request without reading it
    scoring = [r for r in routes if "POST" in getattr(r, "methods", ()) and not r.path.startswith("/v2/repository")]
    app.add_middleware(AdmissionControl, routes=scoring, max_concurrent=settings.max_concurrent_requests,
                       default_timeout_s=settings.request_timeout_s, retry_after_s=settings.retry_after_s,
                       metrics=app.state.metrics, in_flight=app.state.in_flight,
                       queue=lambda: app.state.batcher)
    if settings.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins, allow_methods=["GET", "POST"],
                           allow_headers=["Content-Type", "X-API-Key"])
    app.add_middleware(MetricsMiddleware, metrics=app.state.metrics, routes=routes)
    # outermost: every answer carries the request id, every request gets its log line
    app.add_middleware(RequestLog, logger="service.access", enabled=settings.access_log)
    if tracer_provider is not None:  # outermost of all: the server span covers the request's whole life
        instrument_app(app, tracer_provider)
    return app
