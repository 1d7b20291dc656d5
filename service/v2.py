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

**Binary tensor extension** (``binary_tensor_data``, as Triton defines it), because Triton's and
KServe's HTTP clients use it by default (``tritonclient.http`` sends every input as binary unless
told otherwise, and asks for binary outputs): the body is a JSON header of
``Inference-Header-Content-Length`` bytes followed by the raw bytes of every input whose
``parameters.binary_data_size`` is set, in input order (little-endian, row-major; a ``BYTES``
element is a 4-byte little-endian length and its bytes). A binary ``BYTES`` image holds the PNG or
JPEG file itself (or, if it does not start with a PNG/JPEG signature, its base64 text). Outputs are
binary when they ask for ``parameters.binary_data: true``, or when the request's
``parameters.binary_data_output`` is true and they do not ask otherwise; the answer is then framed
the same way (``Inference-Header-Content-Length`` header, ``application/octet-stream``). Broken
framing is refused before anything is decoded: a header length that is not a number or exceeds the
body (400 ``inference_header_length``), sizes that do not match the shape and datatype or do not
add up to the body (422 ``binary_data_size``), ``data`` and ``binary_data_size`` on one input (422
``binary_data``). Shared-memory extensions are not implemented.
"""

from __future__ import annotations

import json
import math
import struct
import time
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from typing import Any

import numpy as np
from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, Response

from firp.core.contract import PLAN_WIDTH
from service.deps import (
    check_batch_size,
    image_digest,
    ready_model,
    score_off_loop,
    settings_of,
)
from service.errors import ServiceError, error_responses
from service.guard import BINARY_HEADER
from service.images import ImageLimits, check_dimensions, decode_base64_image, decode_image_bytes, image_from_array
from service.schemas import (
    V2InferRequest,
    V2InferResponse,
    V2Live,
    V2ModelMetadata,
    V2ModelReady,
    V2Ready,
    V2RequestInput,
    V2ServerMetadata,
    V2TensorMetadata,
)
from service.routing import FastJSONRoute
from service.scorer import ModelScores, ServiceModel

__all__ = ["BINARY_EXTENSION", "OUTPUT_NAMES", "V2InferRoute", "v2_router"]

SERVER_NAME = "firp-service"
SERVER_VERSION = "1.0.0"
PLATFORM = "firp_ensemble"
OUTPUT_NAMES = ("score", "success", "spread", "member_scores", "failure_step", "attention")
#: The extension's name in the server metadata (Triton's name for it).
BINARY_EXTENSION = "binary_tensor_data"
#: Where :class:`V2InferRoute` leaves a binary request's tensor bytes for the endpoint.
SCOPE_BINARY = "firp.v2.binary"
#: Element sizes of the datatypes this model reads or writes as binary (little-endian).
_DTYPES = {"UINT8": np.dtype("u1"), "FP32": np.dtype("<f4"), "FP64": np.dtype("<f8"), "INT64": np.dtype("<i8"),
           "BOOL": np.dtype("?")}
_IMAGE_SIGNATURES = (b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff")

_INFER_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {"description": "JSON, or with any binary output the binary tensor extension's framing: a JSON header of "
                         "Inference-Header-Content-Length bytes, then the binary outputs' bytes",
          "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}},
    **error_responses(400, 401, 404, 413, 415, 422, 503),
}
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
# binary framing (the route class) and the binary section of a request
# ------------------------------------------------------------------------------------------


def _header_length(declared: str, body_size: int) -> int:
    """The ``Inference-Header-Content-Length`` value, checked against the body (400 if broken)."""
    if not declared.strip().isdigit():
        raise ServiceError(400, BINARY_HEADER, "inference_header_length",
                           f"{BINARY_HEADER} must be a non-negative integer, got {declared!r}")
    n = int(declared)
    if n > body_size:
        raise ServiceError(400, BINARY_HEADER, "inference_header_length",
                           f"{BINARY_HEADER} is {n} but the body has only {body_size} bytes")
    return n


class V2InferRoute(FastJSONRoute):
    """The V2 inference routes: unframe a binary-extension body before FastAPI reads it.

    A body with ``Inference-Header-Content-Length`` is split into its JSON header, which FastAPI
    then parses and validates as any JSON body (same errors, same OpenAPI schema), and its binary
    section, left in the scope for the endpoint. A body without the header is JSON; a missing
    Content-Type (Triton's clients send none) is read as JSON too. The guard
    (:class:`service.guard.RequestGuard`) has already bounded the body's size.
    """

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def route_handler(request: Request) -> Response:
            declared = request.headers.get(BINARY_HEADER)
            if declared is None and request.headers.get("content-type") is not None:
                return await handler(request)
            body = await request.body()
            binary = None
            if declared is not None:
                n = _header_length(declared, len(body))
                body, binary = body[:n], body[n:]
                try:
                    body.decode("utf-8")
                except UnicodeDecodeError as exc:
                    raise ServiceError(422, "body", "json_invalid", f"the JSON header is not UTF-8 text ({exc.reason} "
                                       f"at byte {exc.start})") from None
            scope = dict(request.scope)
            scope[SCOPE_BINARY] = binary
            scope["headers"] = [(k, v) for k, v in request.scope["headers"] if k not in (b"content-type", b"content-length")]
            scope["headers"] += [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
            sent = False

            async def receive() -> dict[str, Any]:
                nonlocal sent
                if not sent:
                    sent = True
                    return {"type": "http.request", "body": body, "more_body": False}
                return await request.receive()

            return await handler(Request(scope, receive))

        return route_handler


@dataclass
class _Binary:
    """The binary section of a request, handed out input by input in order."""

    data: bytes | None  # None: the request had no Inference-Header-Content-Length
    offset: int = 0

    def take(self, inp: V2RequestInput, field: str) -> bytes | None:
        """This input's raw bytes, or None if it carries its elements in ``data``."""
        params = inp.parameters or {}
        size = params.get("binary_data_size")
        if size is None:
            if inp.data is None:
                raise ServiceError(422, f"{field}.data", "binary_data",
                                   "an input needs data, or parameters.binary_data_size with its bytes after the header")
            return None
        where = f"{field}.parameters.binary_data_size"
        if isinstance(size, bool) or not isinstance(size, int) or size < 0:
            raise ServiceError(422, where, "binary_data_size", f"must be a non-negative integer, got {size!r}")
        if inp.data is not None:
            raise ServiceError(422, f"{field}.data", "binary_data", "an input has either data or binary_data_size, not both")
        if self.data is None:
            raise ServiceError(422, where, "binary_data_size",
                               f"binary data needs the {BINARY_HEADER} header (the JSON header's length in bytes)")
        if self.offset + size > len(self.data):
            raise ServiceError(422, where, "binary_data_size",
                               f"{size} bytes asked for at offset {self.offset} of the binary data, which has only "
                               f"{len(self.data)} bytes")
        raw = self.data[self.offset: self.offset + size]
        self.offset += size
        return raw

    def check_consumed(self) -> None:
        if self.data is not None and self.offset != len(self.data):
            raise ServiceError(422, "inputs", "binary_data_size",
                               f"the inputs' binary_data_size add up to {self.offset} bytes, but {len(self.data)} bytes "
                               "follow the JSON header")


def _bytes_elements(raw: bytes, count: int, field: str) -> list[bytes]:
    """A binary BYTES tensor: ``count`` elements, each a 4-byte little-endian length and its bytes."""
    out, offset = [], 0
    for i in range(count):
        if offset + 4 > len(raw):
            raise ServiceError(422, f"{field}.parameters.binary_data_size", "binary_data_size",
                               f"BYTES element {i}: no 4-byte length at offset {offset} of {len(raw)} bytes")
        (n,) = struct.unpack_from("<I", raw, offset)
        offset += 4
        if offset + n > len(raw):
            raise ServiceError(422, f"{field}.parameters.binary_data_size", "binary_data_size",
                               f"BYTES element {i} declares {n} bytes but only {len(raw) - offset} follow")
        out.append(raw[offset: offset + n])
        offset += n
    if offset != len(raw):
        raise ServiceError(422, f"{field}.parameters.binary_data_size", "binary_data_size",
                           f"{len(raw) - offset} bytes left over after {count} BYTES element(s)")
    return out


# ------------------------------------------------------------------------------------------
# tensors in
# ------------------------------------------------------------------------------------------


def _check_shape(inp: V2RequestInput, field: str) -> None:
    if any(d < 0 for d in inp.shape):
        raise ServiceError(422, f"{field}.shape", "shape", f"dimensions must be >= 0, got {inp.shape}")


def _tensor(inp: V2RequestInput, field: str, kinds: str, what: str, raw: bytes | None = None) -> np.ndarray:
    """The input's elements as an array of ``inp.shape``: from ``raw`` (binary, read as the
    datatype's little-endian type) or from ``inp.data`` (JSON; elements of numpy kinds ``kinds``)."""
    _check_shape(inp, field)
    count = math.prod(inp.shape)
    if raw is not None:
        dtype = _DTYPES[inp.datatype]
        if len(raw) != count * dtype.itemsize:
            raise ServiceError(422, f"{field}.parameters.binary_data_size", "binary_data_size",
                               f"shape {inp.shape} of {inp.datatype} needs {count * dtype.itemsize} bytes, "
                               f"binary_data_size is {len(raw)}")
        return np.frombuffer(raw, dtype=dtype).reshape(inp.shape)
    try:
        arr = np.asarray(inp.data)
    except (ValueError, TypeError, OverflowError, RecursionError):
        raise ServiceError(422, f"{field}.data", "data", "data must be a (flat or nested) array of numbers") from None
    if arr.dtype.kind not in kinds:
        raise ServiceError(422, f"{field}.data", "data", f"data must hold {what}, got elements of dtype {arr.dtype}")
    if arr.size != count:
        raise ServiceError(422, f"{field}.data", "shape",
                           f"shape {inp.shape} needs {count} elements, data has {arr.size}")
    return arr.reshape(inp.shape)


def _image_input(inp: V2RequestInput, field: str, limits: ImageLimits, raw: bytes | None) -> tuple[bytes, Any]:
    """(cache key, loader) for the image tensor (``raw``: its binary data, if sent so); cheap checks
    now, decoding in the loader."""
    if inp.datatype == "BYTES":
        if inp.shape not in ([1], [1, 1]):
            raise ServiceError(422, f"{field}.data", "shape", "a BYTES image is shape [1] holding one PNG/JPEG")
        if raw is not None:
            (element,) = _bytes_elements(raw, 1, field)
            if element.startswith(_IMAGE_SIGNATURES):
                return image_digest(b"file", element), lambda: decode_image_bytes(element, limits, field)
            try:
                text = element.decode("ascii")
            except UnicodeDecodeError:
                raise ServiceError(422, field, "format", "a binary BYTES image is a PNG or JPEG file, or its base64 "
                                   "text") from None
        else:
            if inp.data is None or len(inp.data) != 1 or not isinstance(inp.data[0], str):
                raise ServiceError(422, f"{field}.data", "shape",
                                   "a BYTES image is shape [1] holding one base64 PNG/JPEG string")
            text = inp.data[0]
        return image_digest(b"b64", text.encode("utf-8", "surrogatepass")), lambda: decode_base64_image(text, limits, field)
    if inp.datatype != "UINT8":
        raise ServiceError(422, f"{field}.datatype", "datatype", f"image must be UINT8 or BYTES, got {inp.datatype!r}")
    shape = inp.shape[1:] if len(inp.shape) == 4 and inp.shape[0] == 1 else inp.shape
    if len(shape) != 3 or shape[2] != 3:
        raise ServiceError(422, f"{field}.shape", "shape", f"an image is [H, W, 3] or [1, H, W, 3], got {inp.shape}")
    check_dimensions(shape[1], shape[0], limits, field)  # before touching the data
    arr = _tensor(inp, field, "iu", "integers", raw)
    if arr.dtype != np.uint8 and arr.size and (arr.min() < 0 or arr.max() > 255):
        raise ServiceError(422, f"{field}.data", "range", "UINT8 values must lie in [0, 255]")
    pixels = image_from_array(arr.reshape(shape).astype(np.uint8), limits, field)
    key = image_digest(b"px", str(pixels.shape).encode(), pixels.tobytes())
    return key, lambda: pixels


def _plan_input(inp: V2RequestInput, field: str, max_batch: int, raw: bytes | None) -> tuple[list[np.ndarray], list[str]]:
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
    arr = _tensor(inp, field, "iuf", "numbers", raw).astype(np.float64)
    plans = [arr] if n == 1 and arr.ndim == 2 else list(arr)
    return plans, fields


# ------------------------------------------------------------------------------------------
# tensors out
# ------------------------------------------------------------------------------------------


def _output_arrays(scores: ModelScores) -> dict[str, tuple[str, np.ndarray]]:
    """Every output this call has: name -> (datatype, array)."""
    out = {
        "score": ("FP32", np.asarray(scores.probabilities, dtype=np.float32)),
        "success": ("BOOL", np.asarray(scores.success, dtype=bool)),
        "spread": ("FP32", np.asarray(scores.spread, dtype=np.float32)),
        "member_scores": ("FP32", np.asarray(scores.member_probabilities, dtype=np.float32)),
        "failure_step": ("INT64", np.array([-1 if s is None else s for s in scores.failure_steps], dtype=np.int64)),
    }
    if all(a is not None for a in scores.attention):
        out["attention"] = ("FP32", np.stack(scores.attention).astype(np.float32))  # one request = one plan length
    return out


def _binary_flag(params: dict[str, Any] | None, key: str, field: str) -> bool | None:
    """``params[key]`` if given (must be a boolean), else None; ``field`` names the owner ("" = the request)."""
    value = (params or {}).get(key)
    if value is not None and not isinstance(value, bool):
        where = f"{field}.parameters.{key}" if field else f"parameters.{key}"
        raise ServiceError(422, where, key, f"must be true or false, got {value!r}")
    return value


def _response(head: dict[str, Any], scores: ModelScores, wanted: list[tuple[str, bool]]) -> Response:
    """The infer answer: JSON, or (any binary output) a JSON header + the outputs' bytes."""
    arrays = _output_arrays(scores)
    outputs, chunks = [], []
    for name, binary in wanted:
        if name not in arrays:
            continue  # attention of members without attention: nothing to send
        datatype, arr = arrays[name]
        entry: dict[str, Any] = {"name": name, "shape": list(arr.shape), "datatype": datatype}
        if binary:
            raw = np.ascontiguousarray(arr, dtype=_DTYPES[datatype]).tobytes()
            entry["parameters"] = {"binary_data_size": len(raw)}
            chunks.append(raw)
        else:
            entry["data"] = arr.ravel().tolist()
        outputs.append(entry)
    head["outputs"] = outputs
    if not chunks:
        return JSONResponse(head)
    header = json.dumps(head, ensure_ascii=False, allow_nan=False, separators=(",", ":")).encode("utf-8")
    return Response(header + b"".join(chunks), media_type="application/octet-stream",
                    headers={BINARY_HEADER: str(len(header))})


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

    @router.get("", response_model=V2ServerMetadata, dependencies=guarded, responses=error_responses(401),
                summary="V2 server metadata")
    async def server_metadata() -> V2ServerMetadata:
        return V2ServerMetadata(name=SERVER_NAME, version=SERVER_VERSION, extensions=[BINARY_EXTENSION])

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

    async def infer(name: str, version: str | None, body: V2InferRequest, request: Request) -> Response:
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
        default_binary = _binary_flag(body.parameters, "binary_data_output", "") or False
        if body.outputs is not None:
            wanted: list[tuple[str, bool]] = []
            for i, o in enumerate(body.outputs):
                if o.name not in OUTPUT_NAMES:
                    raise ServiceError(422, f"outputs[{i}].name", "unknown_output",
                                       f"outputs are {', '.join(OUTPUT_NAMES)}; got {o.name!r}")
                flag = _binary_flag(o.parameters, "binary_data", f"outputs[{i}]")
                wanted.append((o.name, default_binary if flag is None else flag))
        else:
            wanted = [(name, default_binary) for name in OUTPUT_NAMES]
        # every input's binary data, cut in request order (the extension's order), all of it used
        binary = _Binary(request.scope.get(SCOPE_BINARY))
        raws = [binary.take(inp, f"inputs[{i}]") for i, inp in enumerate(body.inputs)]
        binary.check_consumed()
        i_img, i_plan = seen["image"], seen["plan"]
        key, load_image = _image_input(body.inputs[i_img], f"inputs[{i_img}]", limits, raws[i_img])
        plans, fields = _plan_input(body.inputs[i_plan], f"inputs[{i_plan}]", settings.max_batch, raws[i_plan])
        scores = await score_off_loop(request, model, "/v2/infer", key, load_image, plans, fields)
        head: dict[str, Any] = {
            "model_name": model.name, "model_version": model.version, "id": body.id,
            "parameters": {"threshold": scores.threshold, "elapsed_ms": (time.perf_counter() - start) * 1000.0},
        }
        return _response(head, scores, wanted)

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
