"""The V2 routes: server and model health and metadata, and inference (see :mod:`service.v2`)."""

from __future__ import annotations

import time
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, Response

from firp.core.contract import PLAN_WIDTH
from service.admission import MAX_TIMEOUT_S, tighten_deadline
from service.deps import ready_model, score_off_loop, settings_of
from service.errors import ServiceError, error_responses
from service.images import ImageLimits
from service.routing import FastJSONRoute
from service.schemas import (
    V2InferRequest,
    V2InferResponse,
    V2Live,
    V2ModelMetadata,
    V2ModelReady,
    V2Ready,
    V2ServerMetadata,
    V2TensorMetadata,
)
from service.scorer import ServiceModel
from service.v2.codec import (
    BINARY_EXTENSION,
    OUTPUT_NAMES,
    SCOPE_BINARY,
    Binary,
    V2InferRoute,
    binary_flag,
    image_input,
    plan_input,
    response,
)

__all__ = ["v2_router"]

SERVER_NAME = "firp-service"
SERVER_VERSION = "1.0.0"
PLATFORM = "firp_ensemble"

_INFER_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {"description": "JSON, or with any binary output the binary tensor extension's framing: a JSON header of "
                         "Inference-Header-Content-Length bytes, then the binary outputs' bytes",
          "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}},
    **error_responses(400, 401, 404, 413, 415, 422, 503, 504, v2=True),
}
_GET_ERRORS = error_responses(401, 404, 503, v2=True)


def _named_model(request: Request, name: str, version: str | None = None) -> ServiceModel:
    model = ready_model(request)
    if name != model.name:
        raise ServiceError(404, "model_name", "unknown_model", f"this service serves model {model.name!r}, not {name!r}")
    if version is not None and version != model.version:
        raise ServiceError(404, "model_version", "unknown_version",
                           f"model {model.name!r} is at version {model.version!r}, not {version!r}")
    return model


def _timeout_parameter(parameters: dict[str, Any] | None) -> float | None:
    """``parameters.timeout``: microseconds, an integer >= 0 (0: none), as Triton's schedule-policy extension."""
    value = (parameters or {}).get("timeout")
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_TIMEOUT_S * 1e6:
        raise ServiceError(422, "parameters.timeout", "timeout", "parameters.timeout is microseconds, an integer in "
                           f"[0, {int(MAX_TIMEOUT_S * 1e6)}] (0: no timeout), got {value!r}")
    return value / 1e6 if value else None


def _metadata(model: ServiceModel) -> V2ModelMetadata:
    outputs = [
        V2TensorMetadata(name="score", datatype="FP32", shape=[-1]),
        V2TensorMetadata(name="success", datatype="BOOL", shape=[-1]),
        V2TensorMetadata(name="spread", datatype="FP32", shape=[-1]),
        V2TensorMetadata(name="member_scores", datatype="FP32", shape=[-1, model.n_members]),
        V2TensorMetadata(name="failure_step", datatype="INT64", shape=[-1]),
        V2TensorMetadata(name="attention", datatype="FP32", shape=[-1, -1]),
    ]
    return V2ModelMetadata(
        name=model.name, versions=[model.version], platform=PLATFORM,
        inputs=[V2TensorMetadata(name="image", datatype="UINT8", shape=[-1, -1, 3]),
                V2TensorMetadata(name="plan", datatype="FP32", shape=[-1, PLAN_WIDTH])],
        outputs=outputs,
    )


def v2_router(guarded: list[Any]) -> APIRouter:
    """The V2 routes; ``guarded`` (the API key dependency, or nothing) on all but the health routes."""
    router = APIRouter(prefix="/v2", tags=["open inference protocol (KServe V2)"], route_class=FastJSONRoute)

    @router.get("/health/live", response_model=V2Live, summary="V2 server live")
    async def live() -> V2Live:
        return V2Live(live=True)

    @router.get("/health/ready", response_model=V2Ready, summary="V2 server ready (200) or not (503)",
                responses={503: {"model": V2Ready, "description": "starting or stopping"}})
    async def ready(request: Request) -> Response:
        is_ready = request.app.state.phase == "ready"
        return JSONResponse(V2Ready(ready=is_ready).model_dump(), status_code=200 if is_ready else 503)

    @router.get("", response_model=V2ServerMetadata, dependencies=guarded, responses=error_responses(401, v2=True),
                summary="V2 server metadata")
    async def server_metadata() -> V2ServerMetadata:
        return V2ServerMetadata(name=SERVER_NAME, version=SERVER_VERSION,
                                extensions=[BINARY_EXTENSION, "model_repository", "statistics", "schedule_policy"])

    @router.get("/models/stats", dependencies=guarded, responses=_GET_ERRORS,
                summary="V2 statistics extension: every model's inference statistics")  # before /models/{name}
    async def all_statistics(request: Request) -> dict:
        model = ready_model(request)
        return {"model_stats": [model.statistics.as_dict(model.name, model.version)]}

    @router.get("/models/{name}", response_model=V2ModelMetadata, dependencies=guarded, responses=_GET_ERRORS,
                summary="V2 model metadata")
    async def model_metadata(name: str, request: Request) -> V2ModelMetadata:
        return _metadata(_named_model(request, name))

    @router.get("/models/{name}/versions/{version}", response_model=V2ModelMetadata, dependencies=guarded,
                responses=_GET_ERRORS, summary="V2 model metadata (one version)")
    async def model_version_metadata(name: str, version: str, request: Request) -> V2ModelMetadata:
        return _metadata(_named_model(request, name, version))

    @router.get("/models/{name}/ready", response_model=V2ModelReady, dependencies=guarded, responses=_GET_ERRORS,
                summary="V2 model ready")
    async def model_ready(name: str, request: Request) -> V2ModelReady:
        return V2ModelReady(name=_named_model(request, name).name, ready=True)

    @router.get("/models/{name}/versions/{version}/ready", response_model=V2ModelReady, dependencies=guarded,
                responses=_GET_ERRORS, summary="V2 model ready (one version)")
    async def model_version_ready(name: str, version: str, request: Request) -> V2ModelReady:
        return V2ModelReady(name=_named_model(request, name, version).name, ready=True)

    @router.get("/models/{name}/stats", dependencies=guarded, responses=_GET_ERRORS,
                summary="V2 statistics extension: the model's inference statistics")
    async def statistics(name: str, request: Request) -> dict:
        model = _named_model(request, name)
        return {"model_stats": [model.statistics.as_dict(model.name, model.version)]}

    @router.get("/models/{name}/versions/{version}/stats", dependencies=guarded, responses=_GET_ERRORS,
                summary="V2 statistics extension: one version's inference statistics")
    async def version_statistics(name: str, version: str, request: Request) -> dict:
        model = _named_model(request, name, version)
        return {"model_stats": [model.statistics.as_dict(model.name, model.version)]}

    async def infer(name: str, version: str | None, body: V2InferRequest, request: Request) -> Response:
        start = time.perf_counter()
        model = _named_model(request, name, version)
        # KServe's client repeats the path's model in the body; it must agree with the path
        for key, value, in_path in (("model_name", body.model_name, name), ("model_version", body.model_version, version)):
            if value is not None and in_path is not None and value != in_path:
                raise ServiceError(422, key, "path_mismatch", f"{key} {value!r} in the body differs from the path's "
                                   f"{in_path!r}")
            if key == "model_version" and value is not None and in_path is None and value != model.version:
                raise ServiceError(404, key, "unknown_version",
                                   f"model {model.name!r} is at version {model.version!r}, not {value!r}")
        budget = _timeout_parameter(body.parameters)
        if budget is not None:
            tighten_deadline(request, budget)
        settings = settings_of(request)
        limits = ImageLimits.from_settings(settings)
        seen: dict[str, int] = {}
        for i, inp in enumerate(body.inputs):
            if inp.name not in ("image", "plan"):
                raise ServiceError(422, f"inputs[{i}].name", "unknown_input",
                                   f"inputs are 'image' and 'plan', got {inp.name!r}")
            if inp.name in seen:
                raise ServiceError(422, f"inputs[{i}].name", "duplicate_input", f"input {inp.name!r} given twice")
            seen[inp.name] = i
        for needed in ("image", "plan"):
            if needed not in seen:
                raise ServiceError(422, "inputs", "missing_input", f"input {needed!r} is missing")
        default_binary = binary_flag(body.parameters, "binary_data_output", "") or False
        if body.outputs is not None:
            wanted: list[tuple[str, bool]] = []
            for i, o in enumerate(body.outputs):
                if o.name not in OUTPUT_NAMES:
                    raise ServiceError(422, f"outputs[{i}].name", "unknown_output",
                                       f"outputs are {', '.join(OUTPUT_NAMES)}; got {o.name!r}")
                flag = binary_flag(o.parameters, "binary_data", f"outputs[{i}]")
                wanted.append((o.name, default_binary if flag is None else flag))
        else:
            wanted = [(name, default_binary) for name in OUTPUT_NAMES]
        # every input's binary data, cut in request order (the extension's order), all of it used
        binary = Binary(request.scope.get(SCOPE_BINARY))
        raws = [binary.take(inp, f"inputs[{i}]") for i, inp in enumerate(body.inputs)]
        binary.check_consumed()
        i_img, i_plan = seen["image"], seen["plan"]
        key, load_image = image_input(body.inputs[i_img], f"inputs[{i_img}]", limits, raws[i_img])
        plans, fields = plan_input(body.inputs[i_plan], f"inputs[{i_plan}]", settings.max_batch, raws[i_plan])
        scores = await score_off_loop(request, model, "/v2/infer", key, load_image, plans, fields)
        head: dict[str, Any] = {
            "model_name": scores.name or model.name, "model_version": scores.version or model.version, "id": body.id,
            "parameters": {"threshold": scores.threshold, "elapsed_ms": (time.perf_counter() - start) * 1000.0},
        }
        return response(head, scores, wanted)

    async def infer_latest(name: str, body: V2InferRequest, request: Request) -> Response:
        return await infer(name, None, body, request)

    async def infer_version(name: str, version: str, body: V2InferRequest, request: Request) -> Response:
        return await infer(name, version, body, request)

    for path, endpoint, summary in (
        ("/models/{name}/infer", infer_latest, "V2 inference: score plans for an image"),
        ("/models/{name}/versions/{version}/infer", infer_version, "V2 inference on one model version"),
    ):
        router.add_api_route(path, endpoint, methods=["POST"], response_model=V2InferResponse, dependencies=guarded,
                             responses=_INFER_RESPONSES, summary=summary, route_class_override=V2InferRoute)

    return router
