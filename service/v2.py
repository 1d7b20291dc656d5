"""Open Inference Protocol (KServe V2 / Triton HTTP/REST, JSON tensors) for the same model.

Why: a KServe or Triton HTTP client (``tritonclient.http``, ``kserve.InferenceRESTClient``) can
call the service unchanged, and tools built on the protocol (load generators, gateways) work.

The model, as the protocol sees it (``GET /v2/models/{name}``; ``name`` is the bundle's name):

* inputs -- ``image``: ``UINT8`` ``[H, W, 3]`` (or ``[1, H, W, 3]``), or ``BYTES`` ``[1]`` holding a
  base64 PNG/JPEG as in /v1; ``plan``: ``FP32`` (or ``FP64``) ``[T, 16]``, or ``[N, T, 16]`` for N
  candidate plans of equal length.
* outputs, N = number of plans -- ``score`` FP32 [N], ``success`` BOOL [N], ``spread`` FP32 [N],
  ``member_scores`` FP32 [N, M], ``failure_step`` INT64 [N] (-1: none), ``attention`` FP32 [N, T]
  (only if the members have attention). ``outputs`` in the request selects a subset.
* response ``parameters``: ``threshold``, ``elapsed_ms``.

Tensor data may be flat (row-major, as the protocol specifies) or nested. Health routes stay open;
the others need the API key when one is configured. Errors use the service's one error shape (the
protocol's ``{"error": "<message>"}`` is a string there; clients read ``error`` either way).
Extensions (binary tensor data, shared memory) are not implemented.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, Response

from firp.contract import PLAN_WIDTH
from service.deps import (
    check_batch_size,
    image_digest,
    ready_model,
    score_off_loop,
    settings_of,
)
from service.errors import ServiceError, error_responses
from service.images import ImageLimits, check_dimensions, decode_base64_image, image_from_array
from service.schemas import (
    V2InferRequest,
    V2InferResponse,
    V2Live,
    V2ModelMetadata,
    V2ModelReady,
    V2Ready,
    V2RequestInput,
    V2ResponseOutput,
    V2ServerMetadata,
    V2TensorMetadata,
)
from service.scorer import ModelScores, ServiceModel

__all__ = ["OUTPUT_NAMES", "v2_router"]

SERVER_NAME = "firp-service"
SERVER_VERSION = "1.0.0"
PLATFORM = "firp_ensemble"
OUTPUT_NAMES = ("score", "success", "spread", "member_scores", "failure_step", "attention")

_INFER_ERRORS = error_responses(401, 404, 413, 415, 422, 503)
_GET_ERRORS = error_responses(401, 404, 503)


def _named_model(request: Request, name: str, version: str | None = None) -> ServiceModel:
    model = ready_model(request)
    if name != model.name:
        raise ServiceError(404, "model_name", "unknown_model", f"this service serves model {model.name!r}, not {name!r}")
    if version is not None and version != model.version:
        raise ServiceError(404, "model_version", "unknown_version",
                           f"model {model.name!r} is at version {model.version!r}, not {version!r}")
    return model


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


# ------------------------------------------------------------------------------------------
# tensors in
# ------------------------------------------------------------------------------------------


def _tensor(inp: V2RequestInput, field: str, kinds: str, what: str) -> np.ndarray:
    """``inp.data`` as an array of ``inp.shape``; elements must be of numpy kinds ``kinds``."""
    if any(d < 0 for d in inp.shape):
        raise ServiceError(422, f"{field}.shape", "shape", f"dimensions must be >= 0, got {inp.shape}")
    try:
        arr = np.asarray(inp.data)
    except (ValueError, TypeError, OverflowError, RecursionError):
        raise ServiceError(422, f"{field}.data", "data", "data must be a (flat or nested) array of numbers") from None
    if arr.dtype.kind not in kinds:
        raise ServiceError(422, f"{field}.data", "data", f"data must hold {what}, got elements of dtype {arr.dtype}")
    if arr.size != math.prod(inp.shape):
        raise ServiceError(422, f"{field}.data", "shape",
                           f"shape {inp.shape} needs {math.prod(inp.shape)} elements, data has {arr.size}")
    return arr.reshape(inp.shape)


def _image_input(inp: V2RequestInput, field: str, limits: ImageLimits) -> tuple[bytes, Any]:
    """(cache key, loader) for the image tensor; cheap checks now, decoding in the loader."""
    if inp.datatype == "BYTES":
        if inp.shape not in ([1], [1, 1]) or len(inp.data) != 1 or not isinstance(inp.data[0], str):
            raise ServiceError(422, f"{field}.data", "shape",
                               "a BYTES image is shape [1] holding one base64 PNG/JPEG string")
        text: str = inp.data[0]
        return image_digest(b"b64", text.encode("utf-8", "surrogatepass")), lambda: decode_base64_image(text, limits, field)
    if inp.datatype != "UINT8":
        raise ServiceError(422, f"{field}.datatype", "datatype", f"image must be UINT8 or BYTES, got {inp.datatype!r}")
    shape = inp.shape[1:] if len(inp.shape) == 4 and inp.shape[0] == 1 else inp.shape
    if len(shape) != 3 or shape[2] != 3:
        raise ServiceError(422, f"{field}.shape", "shape", f"an image is [H, W, 3] or [1, H, W, 3], got {inp.shape}")
    check_dimensions(shape[1], shape[0], limits, field)  # before touching the data
    arr = _tensor(inp, field, "iu", "integers")
    if arr.size and (arr.min() < 0 or arr.max() > 255):
        raise ServiceError(422, f"{field}.data", "range", "UINT8 values must lie in [0, 255]")
    pixels = image_from_array(arr.reshape(shape).astype(np.uint8), limits, field)
    key = image_digest(b"px", str(pixels.shape).encode(), pixels.tobytes())
    return key, lambda: pixels


def _plan_input(inp: V2RequestInput, field: str, max_batch: int) -> tuple[list[np.ndarray], list[str]]:
    if inp.datatype not in ("FP32", "FP64"):
        raise ServiceError(422, f"{field}.datatype", "datatype", f"plan must be FP32 or FP64, got {inp.datatype!r}")
    if len(inp.shape) == 2:
        n, fields = 1, ["plan"]
    elif len(inp.shape) == 3:
        n = inp.shape[0]
        check_batch_size(n, max_batch, f"{field}.shape")
        fields = [f"plan[{i}]" for i in range(n)]
    else:
        raise ServiceError(422, f"{field}.shape", "shape", f"a plan is [T, {PLAN_WIDTH}] or [N, T, {PLAN_WIDTH}], "
                           f"got {inp.shape}")
    arr = _tensor(inp, field, "iuf", "numbers").astype(np.float64)
    plans = [arr] if n == 1 and arr.ndim == 2 else list(arr)
    return plans, fields


# ------------------------------------------------------------------------------------------
# tensors out
# ------------------------------------------------------------------------------------------


def _outputs(scores: ModelScores, wanted: list[str] | None) -> list[V2ResponseOutput]:
    n = len(scores.probabilities)
    f32 = lambda a: np.asarray(a, dtype=np.float32).ravel().tolist()  # noqa: E731
    out = {
        "score": V2ResponseOutput(name="score", shape=[n], datatype="FP32", data=f32(scores.probabilities)),
        "success": V2ResponseOutput(name="success", shape=[n], datatype="BOOL", data=scores.success.tolist()),
        "spread": V2ResponseOutput(name="spread", shape=[n], datatype="FP32", data=f32(scores.spread)),
        "member_scores": V2ResponseOutput(name="member_scores", shape=list(scores.member_probabilities.shape),
                                          datatype="FP32", data=f32(scores.member_probabilities)),
        "failure_step": V2ResponseOutput(name="failure_step", shape=[n], datatype="INT64",
                                         data=[-1 if s is None else s for s in scores.failure_steps]),
    }
    if all(a is not None for a in scores.attention):
        att = np.stack(scores.attention)  # one request = one plan length, so this stacks
        out["attention"] = V2ResponseOutput(name="attention", shape=list(att.shape), datatype="FP32", data=f32(att))
    names = wanted if wanted is not None else [k for k in OUTPUT_NAMES if k in out]
    return [out[k] for k in names if k in out]


def v2_router(guarded: list[Any]) -> APIRouter:
    """The V2 routes; ``guarded`` (the API key dependency, or nothing) on all but the health routes."""
    router = APIRouter(prefix="/v2", tags=["open inference protocol (KServe V2)"])

    @router.get("/health/live", response_model=V2Live, summary="V2 server live")
    async def live() -> V2Live:
        return V2Live(live=True)

    @router.get("/health/ready", response_model=V2Ready, summary="V2 server ready (200) or not (503)",
                responses={503: {"model": V2Ready, "description": "starting or stopping"}})
    async def ready(request: Request) -> Response:
        is_ready = request.app.state.phase == "ready"
        return JSONResponse(V2Ready(ready=is_ready).model_dump(), status_code=200 if is_ready else 503)

    @router.get("", response_model=V2ServerMetadata, dependencies=guarded, responses=error_responses(401),
                summary="V2 server metadata")
    async def server_metadata() -> V2ServerMetadata:
        return V2ServerMetadata(name=SERVER_NAME, version=SERVER_VERSION, extensions=[])

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

    async def infer(name: str, version: str | None, body: V2InferRequest, request: Request) -> V2InferResponse:
        start = time.perf_counter()
        model = _named_model(request, name, version)
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
        wanted = None
        if body.outputs is not None:
            wanted = []
            for i, o in enumerate(body.outputs):
                if o.name not in OUTPUT_NAMES:
                    raise ServiceError(422, f"outputs[{i}].name", "unknown_output",
                                       f"outputs are {', '.join(OUTPUT_NAMES)}; got {o.name!r}")
                wanted.append(o.name)
        i_img, i_plan = seen["image"], seen["plan"]
        key, load_image = _image_input(body.inputs[i_img], f"inputs[{i_img}]", limits)
        plans, fields = _plan_input(body.inputs[i_plan], f"inputs[{i_plan}]", settings.max_batch)
        scores = await score_off_loop(request, model, "/v2/infer", key, load_image, plans, fields)
        return V2InferResponse(
            model_name=model.name, model_version=model.version, id=body.id,
            parameters={"threshold": scores.threshold, "elapsed_ms": (time.perf_counter() - start) * 1000.0},
            outputs=_outputs(scores, wanted),
        )

    @router.post("/models/{name}/infer", response_model=V2InferResponse, dependencies=guarded,
                 responses=_INFER_ERRORS, summary="V2 inference: score plans for an image")
    async def infer_latest(name: str, body: V2InferRequest, request: Request) -> V2InferResponse:
        return await infer(name, None, body, request)

    @router.post("/models/{name}/versions/{version}/infer", response_model=V2InferResponse, dependencies=guarded,
                 responses=_INFER_ERRORS, summary="V2 inference on one model version")
    async def infer_version(name: str, version: str, body: V2InferRequest, request: Request) -> V2InferResponse:
        return await infer(name, version, body, request)

    return router
