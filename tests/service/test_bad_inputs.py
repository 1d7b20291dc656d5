"""Bad input never yields a 5xx: a table of refusals, each with its status, field, rule and message.

The shared client runs with the small limits of ``conftest.STRICT`` (16 KiB images, 16-256 px
sides, aspect ratio <= 4, <= 4 plans per batch, 256 KiB bodies); the tiny bundle takes T in [8, 16].
"""

from __future__ import annotations

import base64
import io
import json
import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from tests.firp.bundle_helpers import random_image

from .helpers import encode_image, plan_list, plans_list, png_b64

IMAGE = png_b64(40)


def png_claiming(width: int, height: int) -> str:
    """A ~1 KB PNG whose header declares ``width x height`` RGB pixels (a decompression bomb)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    rows = zlib.compress(b"\x00" * (1 + 3 * width) * 4, 9)
    raw = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
           + chunk(b"IDAT", rows) + chunk(b"IEND", b""))
    return base64.b64encode(raw).decode()


def truncated_png() -> str:
    raw = base64.b64decode(png_b64(64, seed=3))
    return base64.b64encode(raw[: len(raw) // 2]).decode()


def gif() -> str:
    buf = io.BytesIO()
    Image.fromarray(random_image(40)).save(buf, format="GIF")
    return base64.b64encode(buf.getvalue()).decode()


def with_cell(t: int, c: int, value: float, plan=None) -> list[list[float]]:
    plan = plan or plan_list(10)
    plan[t][c] = value
    return plan


def not_one_hot() -> list[list[float]]:
    plan = plan_list(10)
    plan[3][:7] = [0.0] * 7
    plan[3][2] = 0.5
    return plan


def raw(text: str) -> dict:
    return {"content": text.encode(), "headers": {"Content-Type": "application/json"}}


def score(**body) -> dict:
    return {"json": {"image": IMAGE, "plan": plan_list(10), **body}}


def batch(**body) -> dict:
    return {"json": {"image": IMAGE, "plans": plans_list(2), **body}}


def with_literal(t: int, c: int, literal: str) -> str:
    """The JSON of a score request whose plan[t][c] is ``literal`` (NaN, 1e999: not expressible in a dict)."""
    return json.dumps({"image": IMAGE, "plan": with_cell(t, c, 12345.678)}).replace("12345.678", literal)

# (id, url, request kwargs, status, field, rule, message fragment)
CASES = [
    # --- the image
    ("not base64", "/v1/score", score(image="this is *not* base64!"), 422, "image", "base64", "base64"),
    ("base64 of text", "/v1/score", score(image=base64.b64encode(b"hello world").decode()), 422, "image", "format",
     "PNG or JPEG"),
    ("a GIF", "/v1/score", score(image=gif()), 422, "image", "format", "PNG or JPEG"),
    ("truncated PNG", "/v1/score", score(image=truncated_png()), 422, "image", "decode", "cannot be decoded"),
    ("decompression bomb", "/v1/score", score(image=png_claiming(5000, 5000)), 422, "image", "dimensions",
     "5000x5000 has a side above the maximum 256"),
    ("PIL-sized decompression bomb", "/v1/score", score(image=png_claiming(50_000, 50_000)), 422, "image",
     "dimensions", "declares too many pixels"),
    ("too many pixels", "/v1/score", score(image=png_claiming(256, 200)), 422, "image", "dimensions",
     "more than 32768 pixels"),
    ("too small", "/v1/score", score(image=png_b64(8)), 422, "image", "dimensions", "below the minimum 16"),
    ("extreme aspect ratio", "/v1/score", score(image=encode_image(random_image(200)[:20])), 422, "image",
     "dimensions", "aspect ratio above 4"),
    ("image over max_image_bytes", "/v1/score", score(image=png_b64(100)), 413, "image", "max_bytes",
     "larger than 16384 bytes"),
    ("image not a string", "/v1/score", score(image=[1, 2, 3]), 422, "image", "string_type", "valid string"),
    # --- the plan (contract rules from firp.core.contract.validate_plan)
    ("plan width 15", "/v1/score", score(plan=[row[:15] for row in plan_list(10)]), 422, "plan", "width",
     "16 numbers"),
    ("T above the bundle's range", "/v1/score", score(plan=plan_list(17)), 422, "plan", "length",
     "T must be in [8, 16], got 17"),
    ("T below the bundle's range", "/v1/score", score(plan=plan_list(12)[:7]), 422, "plan", "length",
     "got 7"),
    ("NaN", "/v1/score", raw(with_literal(2, 9, "NaN")), 422, "plan[2][9]", "finite", "NaN"),
    ("infinity", "/v1/score", raw(with_literal(5, 12, "1e999")), 422, "plan[5][12]", "finite", "infinity"),
    ("-Infinity", "/v1/score", raw(with_literal(0, 3, "-Infinity")), 422, "plan[0][3]", "finite", "infinity"),
    ("not one-hot", "/v1/score", score(plan=not_one_hot()), 422, "plan[3]", "one_hot", "one-hot"),
    ("joint outside its limits", "/v1/score", score(plan=with_cell(4, 10, 3.5)), 422, "plan[4][10]", "joint_limits",
     "joint4 target 3.5000 is outside"),
    ("finger outside its limits", "/v1/score", score(plan=with_cell(2, 15, 0.05)), 422, "plan[2][15]",
     "joint_limits", "finger_joint2"),
    ("a string in the plan", "/v1/score", score(plan=with_cell(1, 8, "0.5")), 422, "plan[1][8]", "float_type",
     "valid number"),
    ("a boolean in the plan", "/v1/score", score(plan=with_cell(1, 0, True)), 422, "plan[1][0]", "float_type",
     "valid number"),
    ("plan missing", "/v1/score", {"json": {"image": IMAGE}}, 422, "plan", "missing", "Field required"),
    ("plan not a list", "/v1/score", score(plan="a plan"), 422, "plan", "list_type", "valid list"),
    # --- the request as a whole
    ("unknown field", "/v1/score", score(plans=[plan_list(10)]), 422, "plans", "extra_forbidden", "not permitted"),
    ("task of another bundle", "/v1/score", score(task="replacement"), 422, "task", "task_mismatch", "replacement"),
    ("request_id too long", "/v1/score", score(request_id="x" * 129), 422, "request_id", "string_too_long",
     "at most 128"),
    ("invalid JSON", "/v1/score", raw('{"image": "abc", "plan": [[1, 2,'), 422, "body", "json_invalid",
     "JSON decode error at character"),
    ("body not UTF-8", "/v1/score", {"content": b'{"image": "\xff\xfe"}', "headers": {"Content-Type": "application/json"}},
     422, "body", "json_invalid", "not UTF-8"),
    ("JSON but not an object", "/v1/score", raw("[1, 2, 3]"), 422, "body", "model_attributes_type", ""),
    ("text/plain body", "/v1/score", {"content": b"{}", "headers": {"Content-Type": "text/plain"}}, 415,
     "Content-Type", "media_type", "text/plain"),
    ("form body", "/v1/score/batch", {"data": {"image": "x"}}, 415, "Content-Type", "media_type",
     "application/x-www-form-urlencoded"),
    ("no content type", "/v1/score", {"content": b"{}"}, 415, "Content-Type", "media_type", "no Content-Type"),
    ("body over the limit", "/v1/score", score(pad="x" * 300_000), 413, "body", "max_body_bytes",
     "larger than 262144 bytes"),
    ("bad Content-Length", "/v1/score", {"content": b"{}", "headers": {"Content-Type": "application/json",
                                                                        "Content-Length": "-5"}},
     400, "Content-Length", "content_length", "non-negative integer"),
    # --- batches
    ("empty batch", "/v1/score/batch", batch(plans=[]), 422, "plans", "batch_size", "between 1 and 4 plans"),
    ("batch above max_batch", "/v1/score/batch", batch(plans=plans_list(5)), 422, "plans", "batch_size", "got 5"),
    ("one bad plan in a batch", "/v1/score/batch", batch(plans=plans_list(2) + [not_one_hot()]), 422, "plans[2][3]",
     "one_hot", "one-hot"),
    ("mixed widths in a batch", "/v1/score/batch", batch(plans=[plan_list(10), [r[:14] for r in plan_list(10)]]),
     422, "plans[1]", "width", "got 14"),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_bad_input_is_a_4xx_naming_field_and_rule(client, case):
    _, url, kwargs, status, field, rule, fragment = case
    r = client.post(url, **kwargs)
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == "application/json"
    body = r.json()
    assert set(body) == {"error"} and set(body["error"]) == {"field", "rule", "message"}
    assert (body["error"]["field"], body["error"]["rule"]) == (field, rule), body
    assert fragment in body["error"]["message"]


def test_a_chunked_body_is_cut_off_at_the_limit(client):
    sent = 0

    async def endless():
        nonlocal sent
        for _ in range(1000):  # 1000 x 4 KiB = 4 MiB, far above the 256 KiB limit
            sent += 4096
            yield b"[" + b"0," * 2046 + b"0"

    r = client.post("/v1/score", content=endless(), headers={"Content-Type": "application/json"})
    assert r.status_code == 413 and r.json()["error"]["rule"] == "max_body_bytes"
    assert "content-length" not in r.request.headers
    assert sent < 512 * 1024  # the service stopped reading soon after the limit


def test_errors_of_other_routes_share_the_shape(client):
    for method, url, status, rule in (("GET", "/no/such/path", 404, "not_found"),
                                      ("GET", "/v1/score", 405, "method_not_allowed"),
                                      ("DELETE", "/v1/model", 405, "method_not_allowed"),
                                      # a body method on a route without it: 405, not 415 (the body is not read)
                                      ("POST", "/v1/model", 405, "method_not_allowed"),
                                      ("PUT", "/v1/score", 405, "method_not_allowed"),
                                      ("POST", "/nothing/here", 404, "not_found")):
        r = client.request(method, url)
        assert r.status_code == status
        assert r.json()["error"]["rule"] == rule and r.json()["error"]["field"] is None


def test_no_bad_input_reaches_the_model_thread_as_an_exception(client):
    """After all the refusals above, the service still answers, and no 5xx was ever counted."""
    assert client.post("/v1/score", json={"image": IMAGE, "plan": plan_list(10)}).status_code == 200
    assert 'status="5' not in client.get("/metrics").text



def test_the_literal_cases_send_what_they_say():
    assert np.isnan(json.loads(with_literal(2, 9, "NaN"))["plan"][2][9])
    assert json.loads(with_literal(5, 12, "1e999"))["plan"][5][12] == float("inf")
