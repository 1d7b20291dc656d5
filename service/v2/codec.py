"""The Open Inference Protocol's tensors as this model reads and writes them: binary framing, inputs, outputs.

Transport apart from the routes (:mod:`service.v2.routes`): how a request's ``image`` and ``plan``
tensors become an image and plans -- JSON data (flat or nested) or the binary tensor extension's raw
bytes after the JSON header -- and how the scores become output tensors, JSON or binary. Broken
framing is refused before anything is decoded (see :mod:`service.v2`).
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from typing import Any

import numpy as np
from fastapi import Request
from fastapi.responses import JSONResponse, Response

from firp.core.contract import PLAN_WIDTH
from service.deps import check_batch_size, image_digest
from service.errors import ServiceError
from service.guard import BINARY_HEADER
from service.images import ImageLimits, check_dimensions, decode_base64_image, decode_image_bytes, image_from_array
from service.routing import FastJSONRoute
from service.scorer import ModelScores
from service.schemas import V2RequestInput

__all__ = ["BINARY_EXTENSION", "OUTPUT_NAMES", "SCOPE_BINARY", "Binary", "V2InferRoute", "binary_flag",
           "image_input", "plan_input", "response"]

#: The extension's name in the server metadata (Triton's name for it).
BINARY_EXTENSION = "binary_tensor_data"
#: Where :class:`V2InferRoute` leaves a binary request's tensor bytes for the endpoint.
SCOPE_BINARY = "firp.v2.binary"
OUTPUT_NAMES = ("score", "success", "spread", "member_scores", "failure_step", "attention")
#: Element sizes of the datatypes this model reads or writes as binary (little-endian).
_DTYPES = {"UINT8": np.dtype("u1"), "FP32": np.dtype("<f4"), "FP64": np.dtype("<f8"), "INT64": np.dtype("<i8"),
           "BOOL": np.dtype("?")}
_IMAGE_SIGNATURES = (b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff")


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
class Binary:
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


def image_input(inp: V2RequestInput, field: str, limits: ImageLimits, raw: bytes | None) -> tuple[bytes, Any]:
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


def plan_input(inp: V2RequestInput, field: str, max_batch: int, raw: bytes | None) -> tuple[list[np.ndarray], list[str]]:
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


def binary_flag(params: dict[str, Any] | None, key: str, field: str) -> bool | None:
    """``params[key]`` if given (must be a boolean), else None; ``field`` names the owner ("" = the request)."""
    value = (params or {}).get(key)
    if value is not None and not isinstance(value, bool):
        where = f"{field}.parameters.{key}" if field else f"parameters.{key}"
        raise ServiceError(422, where, key, f"must be true or false, got {value!r}")
    return value


def response(head: dict[str, Any], scores: ModelScores, wanted: list[tuple[str, bool]]) -> Response:
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


