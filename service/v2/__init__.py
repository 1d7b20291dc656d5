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

from service.v2.codec import BINARY_EXTENSION, OUTPUT_NAMES, V2InferRoute
from service.v2.routes import v2_router

__all__ = ["BINARY_EXTENSION", "OUTPUT_NAMES", "V2InferRoute", "v2_router"]
