"""What every model route needs, shared by the /v1 routes (service.app) and the V2 routes (service.v2):
the loaded model (or a 503), the optional API key, the task check, and scoring off the event loop.
"""

from __future__ import annotations

import hashlib
import hmac
import time
from collections.abc import Callable, Sequence

import numpy as np
from fastapi import Request, Security
from fastapi.security import APIKeyHeader

from firp.core.request_log import SCOPE_LOG
from firp.core.tracing import record_span
from service.admission import deadline_exceeded, deadline_of, release_reservation, remaining
from service.errors import ServiceError
from service.metrics import ServiceMetrics
from service.scorer import JobTimeline, ModelScores, ScoreJob, ServiceModel
from service.settings import ServiceSettings

__all__ = ["API_KEY_HEADER", "check_batch_size", "check_task", "image_digest", "metrics_of", "ready_model",
           "require_api_key", "score_off_loop", "settings_of", "trace_job"]

API_KEY_HEADER = "X-API-Key"

_api_key_scheme = APIKeyHeader(
    name=API_KEY_HEADER, auto_error=False,
    description="Needed on /v1 and /v2 model routes only when the service was started with FIRP_SERVICE_API_KEY.",
)


def settings_of(request: Request) -> ServiceSettings:
    return request.app.state.settings


def metrics_of(request: Request) -> ServiceMetrics:
    return request.app.state.metrics


async def require_api_key(request: Request, key: str | None = Security(_api_key_scheme)) -> None:
    """401 unless the configured API key is sent (no key configured: everyone may call).

    Compared in constant time, so response timing does not leak how much of a guess was right.
    """
    expected = settings_of(request).api_key
    if expected is None:
        return
    if key is None or not hmac.compare_digest(key.encode("utf-8", "surrogatepass"),
                                              expected.get_secret_value().encode("utf-8", "surrogatepass")):
        raise ServiceError(401, API_KEY_HEADER, "api_key", f"missing or wrong {API_KEY_HEADER} header",
                           headers={"WWW-Authenticate": "ApiKey"})


def ready_model(request: Request) -> ServiceModel:
    """The loaded, warmed-up model, or a 503 (``not_ready``) while starting or stopping."""
    model = getattr(request.app.state, "model", None)
    if model is None or request.app.state.phase != "ready":
        raise ServiceError(503, None, "not_ready", f"the model is not ready ({request.app.state.phase})",
                           headers={"Retry-After": "1"})
    return model


def check_task(task: str | None, model: ServiceModel) -> None:
    if task is not None and task != model.task:
        raise ServiceError(422, "task", "task_mismatch",
                           f"this service scores plans for task {model.task!r}, not {task!r}")


def check_batch_size(n: int, limit: int, field: str) -> None:
    if not 1 <= n <= limit:
        raise ServiceError(422, field, "batch_size", f"between 1 and {limit} plans per call, got {n}")


def trace_job(request: Request, timeline: JobTimeline, plans: int, version: str | None,
              error: BaseException | None) -> None:
    """The job's stages as spans of the request's trace (nothing when tracing is off): ``queue wait``
    (the micro-batcher's queue, or the inference token), ``backbone`` (the image decoded and its
    features computed; absent when they were cached) and ``ensemble pass`` (the members over every
    plan of the pass this job shared)."""
    tracer = getattr(request.app.state, "tracer", None)
    if tracer is None or timeline.queued_ns is None:
        return
    failed = None if error is None else (getattr(error, "rule", None) or type(error).__name__)
    if timeline.taken_ns is None:  # answered before a pass took it: dropped at its deadline, or refused
        record_span(tracer, "queue wait", timeline.queued_ns, time.time_ns(), {"firp.plans": plans}, failed)
        return
    record_span(tracer, "queue wait", timeline.queued_ns, timeline.taken_ns, {"firp.plans": plans})
    if timeline.backbone_ns is not None:
        record_span(tracer, "backbone", *timeline.backbone_ns)
    if timeline.members_ns is not None:
        attributes = {"firp.plans": plans, "firp.pass.requests": timeline.pass_jobs,
                      "firp.pass.plans": timeline.pass_plans}
        if version:
            attributes["firp.model.version"] = version
        record_span(tracer, "ensemble pass", *timeline.members_ns, attributes, failed)


def image_digest(kind: bytes, *parts: bytes) -> bytes:
    """The feature cache's key: what the image bytes were (base64 text, or shape + pixels)."""
    h = hashlib.sha256(kind)
    for p in parts:
        h.update(len(p).to_bytes(8, "little"))
        h.update(p)
    return h.digest()


async def score_off_loop(request: Request, model: ServiceModel, endpoint: str, image_key: bytes,
                         load_image: Callable[[], np.ndarray], plans: Sequence[object],
                         fields: Sequence[str]) -> ModelScores:
    """Validate the plans, decode the image if its features are not cached, score: all in the
    model's worker thread (one pass at a time), then record the inference metrics. With
    micro-batching on (:mod:`service.batching`) the job may share its pass with other requests'.
    The request's deadline (:mod:`service.admission`) holds in both paths: work still waiting when it
    passes is never computed."""
    job = ScoreJob(image_key, load_image, plans, fields)
    batcher = getattr(request.app.state, "batcher", None)
    deadline = deadline_of(request)
    started = time.perf_counter()
    try:
        if batcher is not None:
            release_reservation(request.scope)  # from here its plans count as queued
            scores = await batcher.submit(job, deadline)
        else:
            job.timeline.queued_ns = time.time_ns()  # waiting for the inference token

            def work() -> ModelScores:
                job.timeline.taken_ns = time.time_ns()
                left = remaining(deadline)
                if left is not None and left <= 0:  # waited for the inference token past its budget: drop it
                    metrics_of(request).deadline_exceeded.labels("queued").inc()
                    raise deadline_exceeded("queued", None)
                model.statistics.waited(time.perf_counter() - started)
                computing = time.perf_counter()
                result = model.score_jobs([job])[0]
                model.statistics.computed(time.perf_counter() - computing, 1)
                if isinstance(result, BaseException):
                    raise result
                return result

            scores = await model.run(work)
    except BaseException as exc:
        model.statistics.failed(time.perf_counter() - started)
        trace_job(request, job.timeline, len(plans), None, exc)
        raise
    model.statistics.answered(time.perf_counter() - started, len(plans))
    trace_job(request, job.timeline, len(plans), scores.version, None)
    metrics_of(request).observe_inference(endpoint, scores.inference_s, len(plans), scores.cache_hit)
    request.scope.setdefault(SCOPE_LOG, {}).update(model_version=scores.version, plans=len(plans))
    return scores
