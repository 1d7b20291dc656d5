"""KServe V2 binary tensor extension: round trips by hand (in-process) and with Triton's own HTTP
client (``tritonclient.http``, over loopback), and malformed binary bodies refused with a 4xx."""

from __future__ import annotations

import json
import struct
from collections.abc import Iterator

import numpy as np
import pytest

from service.app import create_app
from service.settings import ServiceSettings
from tests.firp.bundle_helpers import random_image, valid_plans

from tests.loopback import serve_on_loopback

from .helpers import encode_image

HEADER = "Inference-Header-Content-Length"
IMG = random_image(40, seed=11)
PLANS = valid_plans(2, 10, seed=12)


def _binary_body(inputs: list[tuple[dict, bytes | None]], **extra) -> tuple[bytes, dict[str, str]]:
    """A binary-extension body: each input's JSON (binary_data_size added when it has bytes), then the bytes."""
    tensors, blobs = [], []
    for spec, raw in inputs:
        spec = dict(spec)
        if raw is not None:
            spec["parameters"] = {**spec.get("parameters", {}), "binary_data_size": len(raw)}
            blobs.append(raw)
        tensors.append(spec)
    header = json.dumps({"inputs": tensors, **extra}).encode()
    return header + b"".join(blobs), {HEADER: str(len(header))}


def _bytes_tensor(*elements: bytes) -> bytes:
    return b"".join(struct.pack("<I", len(e)) + e for e in elements)


def _pixels(image: np.ndarray = IMG) -> tuple[dict, bytes]:
    return {"name": "image", "shape": list(image.shape), "datatype": "UINT8"}, image.tobytes()


def _plans_fp32(plans: np.ndarray = PLANS) -> tuple[dict, bytes]:
    return {"name": "plan", "shape": list(plans.shape), "datatype": "FP32"}, plans.astype("<f4").tobytes()


def _split(response) -> tuple[dict, bytes]:
    n = int(response.headers[HEADER])
    return json.loads(response.content[:n]), response.content[n:]


def _binary_outputs(response) -> dict[str, np.ndarray]:
    head, blob = _split(response)
    out, offset = {}, 0
    for o in head["outputs"]:
        dtype = {"FP32": "<f4", "BOOL": "?", "INT64": "<i8"}[o["datatype"]]
        size = o["parameters"]["binary_data_size"]
        out[o["name"]] = np.frombuffer(blob[offset: offset + size], dtype=dtype).reshape(o["shape"])
        offset += size
    assert offset == len(blob)
    return out


def test_binary_inputs_score_like_json_inputs(client):
    json_body = {"inputs": [
        {"name": "image", "shape": list(IMG.shape), "datatype": "UINT8", "data": IMG.ravel().tolist()},
        {"name": "plan", "shape": list(PLANS.shape), "datatype": "FP32", "data": PLANS.astype(np.float32).ravel().tolist()},
    ]}
    want = {o["name"]: np.array(o["data"]) for o in client.post("/v2/models/tiny/infer", json=json_body).json()["outputs"]}
    body, headers = _binary_body([_pixels(), _plans_fp32()])
    # Triton's clients send no Content-Type at all; the framing header says what the body is
    r = client.post("/v2/models/tiny/infer", content=body, headers=headers)
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("application/json") and HEADER not in r.headers  # JSON outputs
    got = {o["name"]: np.array(o["data"]) for o in r.json()["outputs"]}
    assert list(got) == list(want)
    for name in want:
        np.testing.assert_array_equal(got[name], want[name])


def test_binary_outputs_hold_the_json_values(client):
    body, headers = _binary_body([_plans_fp32(), _pixels()], parameters={"binary_data_output": True}, id="b-1")
    r = client.post("/v2/models/tiny/infer", content=body, headers={**headers, "Content-Type": "application/octet-stream"})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "application/octet-stream"
    head, _ = _split(r)
    assert head["id"] == "b-1" and all("data" not in o for o in head["outputs"])
    binary = _binary_outputs(r)
    body, headers = _binary_body([_plans_fp32(), _pixels()])
    as_json = {o["name"]: o for o in client.post("/v2/models/tiny/infer", content=body, headers=headers).json()["outputs"]}
    for name, arr in binary.items():
        assert list(arr.shape) == as_json[name]["shape"]
        np.testing.assert_array_equal(arr.ravel(), np.array(as_json[name]["data"], dtype=arr.dtype))
    assert binary["member_scores"].shape == (2, 3) and binary["success"].dtype == bool


def test_outputs_choose_binary_one_by_one(client):
    body, headers = _binary_body([_pixels(), _plans_fp32()], parameters={"binary_data_output": True},
                                 outputs=[{"name": "score", "parameters": {"binary_data": False}}, {"name": "spread"}])
    r = client.post("/v2/models/tiny/infer", content=body, headers=headers)
    head, blob = _split(r)
    score, spread = head["outputs"]
    assert "data" in score and "parameters" not in score
    assert spread["parameters"] == {"binary_data_size": 8} and len(blob) == 8
    # and a plain JSON request may ask for one binary output
    json_body = {"inputs": [{"name": "image", "shape": list(IMG.shape), "datatype": "UINT8", "data": IMG.ravel().tolist()},
                            {"name": "plan", "shape": list(PLANS.shape), "datatype": "FP64", "data": PLANS.ravel().tolist()}],
                 "outputs": [{"name": "failure_step", "parameters": {"binary_data": True}}]}
    r = client.post("/v2/models/tiny/infer", json=json_body)
    assert _binary_outputs(r)["failure_step"].dtype == np.int64


def test_bytes_image_as_a_file_or_as_base64_text(client):
    png = encode_image(IMG)
    import base64

    raw_file = base64.b64decode(png)
    body_file, h1 = _binary_body([({"name": "image", "shape": [1], "datatype": "BYTES"}, _bytes_tensor(raw_file)),
                                  _plans_fp32()])
    body_text, h2 = _binary_body([({"name": "image", "shape": [1], "datatype": "BYTES"}, _bytes_tensor(png.encode())),
                                  _plans_fp32()])
    v1 = [client.post("/v1/score", json={"image": png, "plan": p.astype(np.float32).tolist()}).json()["score"] for p in PLANS]
    for body, headers in ((body_file, h1), (body_text, h2)):
        r = client.post("/v2/models/tiny/infer", content=body, headers=headers)
        assert r.status_code == 200, r.text
        score = next(o for o in r.json()["outputs"] if o["name"] == "score")["data"]
        np.testing.assert_allclose(score, v1, atol=1e-6)


def _raw(body: bytes, headers: dict[str, str]) -> dict:
    return {"content": body, "headers": headers}


_OK_BODY, _OK_HEADERS = _binary_body([_pixels(), _plans_fp32()])
_HEADER_LEN = int(_OK_HEADERS[HEADER])
_MALFORMED = [
    ("header length not a number", _raw(_OK_BODY, {HEADER: "12a"}), 400, HEADER, "inference_header_length"),
    ("header length negative", _raw(_OK_BODY, {HEADER: "-5"}), 400, HEADER, "inference_header_length"),
    ("header length beyond the body", _raw(_OK_BODY, {HEADER: str(len(_OK_BODY) + 1)}), 400, HEADER,
     "inference_header_length"),
    ("header cut short", _raw(_OK_BODY, {HEADER: str(_HEADER_LEN - 3)}), 422, "body", "json_invalid"),
    ("header not UTF-8", _raw(b"\xff\xfe" + _OK_BODY, {HEADER: str(_HEADER_LEN + 2)}), 422, "body", "json_invalid"),
    ("binary data missing its last bytes", _raw(_OK_BODY[:-4], _OK_HEADERS), 422, "inputs[1].parameters.binary_data_size",
     "binary_data_size"),
    ("extra bytes after the tensors", _raw(_OK_BODY + b"\0" * 4, _OK_HEADERS), 422, "inputs", "binary_data_size"),
    ("size disagrees with the shape", _raw(*_binary_body([_pixels(), ({"name": "plan", "shape": [2, 10, 16],
                                                                        "datatype": "FP32"}, b"\0" * 100)])),
     422, "inputs[1].parameters.binary_data_size", "binary_data_size"),
    ("size not an integer", _raw(*_binary_body([_pixels(), ({"name": "plan", "shape": [2, 10, 16], "datatype": "FP32",
                                                             "parameters": {"binary_data_size": "1280"}}, None)])),
     422, "inputs[1].parameters.binary_data_size", "binary_data_size"),
    ("binary size without the framing header",
     {"json": {"inputs": [{"name": "image", "shape": list(IMG.shape), "datatype": "UINT8",
                           "parameters": {"binary_data_size": IMG.size}},
                          {"name": "plan", "shape": [2, 10, 16], "datatype": "FP32", "data": PLANS.ravel().tolist()}]}},
     422, "inputs[0].parameters.binary_data_size", "binary_data_size"),
    ("data and binary_data_size both", _raw(*_binary_body([({**_pixels()[0], "data": [0]}, _pixels()[1]), _plans_fp32()])),
     422, "inputs[0].data", "binary_data"),
    ("neither data nor binary_data_size", {"json": {"inputs": [_pixels()[0], {**_plans_fp32()[0], "data": [0.0]}]}},
     422, "inputs[0].data", "binary_data"),
    ("BYTES element longer than its data", _raw(*_binary_body([({"name": "image", "shape": [1], "datatype": "BYTES"},
                                                                 struct.pack("<I", 99) + b"abc"), _plans_fp32()])),
     422, "inputs[0].parameters.binary_data_size", "binary_data_size"),
    ("BYTES element not an image", _raw(*_binary_body([({"name": "image", "shape": [1], "datatype": "BYTES"},
                                                         _bytes_tensor(b"\x00\x01\xfe")), _plans_fp32()])),
     422, "inputs[0]", "format"),
    ("binary_data not a boolean", _raw(*_binary_body([_pixels(), _plans_fp32()],
                                                     outputs=[{"name": "score", "parameters": {"binary_data": 1}}])),
     422, "outputs[0].parameters.binary_data", "binary_data"),
    ("binary_data_output not a boolean", _raw(*_binary_body([_pixels(), _plans_fp32()],
                                                            parameters={"binary_data_output": "yes"})),
     422, "parameters.binary_data_output", "binary_data_output"),
    ("plan bytes that are NaN", _raw(*_binary_body([_pixels(), ({"name": "plan", "shape": [2, 10, 16], "datatype": "FP32"},
                                                                np.full((2, 10, 16), np.nan, "<f4").tobytes())])),
     422, "plan[0][0][0]", "finite"),
]


@pytest.mark.parametrize("case", _MALFORMED, ids=[c[0] for c in _MALFORMED])
def test_malformed_binary_bodies_are_4xx_in_the_error_shape(client, case):
    _, kwargs, status, field, rule = case
    r = client.post("/v2/models/tiny/infer", **kwargs)
    assert r.status_code == status, r.text
    assert (r.json()["field"], r.json()["rule"]) == (field, rule), r.json()


def test_a_binary_body_is_not_taken_by_the_v1_routes(client):
    r = client.post("/v1/score", content=_OK_BODY, headers=_OK_HEADERS)
    assert r.status_code == 415 and r.json()["error"]["rule"] == "media_type"


def test_the_body_limit_holds_for_binary_bodies(client, settings):
    big = b"\0" * (settings.max_body_bytes + 1)
    r = client.post("/v2/models/tiny/infer", content=big, headers={HEADER: "0"})
    assert r.status_code == 413 and r.json()["rule"] == "max_body_bytes"


# ------------------------------------------------------------------------------------------------
# Triton's own client over loopback
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def loopback(settings) -> Iterator[str]:
    """The service in a uvicorn server on a free loopback port, in a thread of this process."""
    with serve_on_loopback(create_app(settings)) as address:
        yield address


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "json"])
def test_tritonclient_scores_equal_v1(loopback, binary):
    """``tritonclient.http.InferenceServerClient`` (binary tensors by default, JSON when told) gets /v1's scores."""
    import httpx
    import tritonclient.http as httpclient  # a dev dependency (pyproject.toml): a missing install must fail here

    triton = httpclient.InferenceServerClient(url=loopback)
    try:
        assert triton.is_server_live() and triton.is_model_ready("tiny")
        assert "binary_tensor_data" in triton.get_server_metadata()["extensions"]
        image = httpclient.InferInput("image", list(IMG.shape), "UINT8")
        image.set_data_from_numpy(IMG, binary_data=binary)
        plan = httpclient.InferInput("plan", list(PLANS.shape), "FP32")
        plan.set_data_from_numpy(PLANS.astype(np.float32), binary_data=binary)
        outputs = [httpclient.InferRequestedOutput(name, binary_data=binary)
                   for name in ("score", "success", "member_scores", "attention")]
        result = triton.infer("tiny", [image, plan], outputs=outputs, request_id="t-1")
        everything = triton.infer("tiny", [image, plan])  # no outputs named: the client asks for all, binary
    finally:
        triton.close()
    png = encode_image(IMG)
    v1 = [httpx.post(f"http://{loopback}/v1/score", json={"image": png, "plan": p.astype(np.float32).tolist()},
                     timeout=30).json() for p in PLANS]
    np.testing.assert_allclose(result.as_numpy("score"), [r["score"] for r in v1], atol=1e-6)
    np.testing.assert_array_equal(result.as_numpy("success"), [r["success"] for r in v1])
    np.testing.assert_allclose(result.as_numpy("member_scores"), [r["member_scores"] for r in v1], atol=1e-6)
    assert result.as_numpy("attention").shape == (2, 10)
    assert result.get_response()["id"] == "t-1"
    np.testing.assert_array_equal(everything.as_numpy("score"), result.as_numpy("score"))
    assert everything.as_numpy("failure_step").dtype == np.int64


def test_tritonclient_drives_the_repository_and_reads_v2_errors(tiny_bundle):
    """Triton's client: versioned readiness, the repository index, unload / load (the hot swap), a
    timeout parameter, the statistics extension, and the protocol's error string in its exception."""
    import tritonclient.http as httpclient
    from tritonclient.utils import InferenceServerException

    with serve_on_loopback(create_app(ServiceSettings(bundle=tiny_bundle))) as address:
        triton = httpclient.InferenceServerClient(url=address)
        try:
            version = triton.get_model_metadata("tiny")["versions"][0]
            assert triton.is_model_ready("tiny", model_version=version)
            assert not triton.is_model_ready("tiny", model_version="0")
            assert triton.get_model_repository_index() == [{"name": "tiny", "version": version, "state": "READY",
                                                            "reason": ""}]
            triton.unload_model("tiny")
            assert not triton.is_server_ready()
            triton.load_model("tiny")  # the configured bundle, read again
            assert triton.is_model_ready("tiny")
            with pytest.raises(InferenceServerException) as err:
                triton.get_model_metadata("other")
            assert "serves model 'tiny', not 'other'" in str(err.value)
            image = httpclient.InferInput("image", list(IMG.shape), "UINT8")
            image.set_data_from_numpy(IMG)
            plan = httpclient.InferInput("plan", list(PLANS.shape), "FP32")
            plan.set_data_from_numpy(PLANS.astype(np.float32))
            result = triton.infer("tiny", [image, plan], timeout=30_000_000)  # microseconds, Triton's own parameter
            assert result.as_numpy("score").shape == (2,)
            # the statistics extension, of the bundle loaded again above: one request of two plans since
            (stats,) = triton.get_inference_statistics("tiny")["model_stats"]
            assert (stats["name"], stats["version"]) == ("tiny", version)
            assert stats["inference_count"] == 2 and stats["execution_count"] == 1
            assert stats["inference_stats"]["success"]["count"] == 1 and stats["inference_stats"]["success"]["ns"] > 0
            assert stats["inference_stats"]["compute_infer"]["ns"] > 0
            assert triton.get_inference_statistics()["model_stats"] == [stats]
            assert triton.get_inference_statistics("tiny", model_version=version)["model_stats"] == [stats]
        finally:
            triton.close()
