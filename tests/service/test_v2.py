"""Open Inference Protocol (KServe V2) routes: health, metadata, inference round trips, refusals."""

from __future__ import annotations

import numpy as np
import pytest

from firp.bundle import load_bundle
from firp.serving import EnsembleScorer
from tests.firp.bundle_helpers import random_image, valid_plans

from .helpers import png_b64


def _infer_body(image: np.ndarray, plans: np.ndarray, **extra) -> dict:
    return {
        "inputs": [
            {"name": "image", "shape": list(image.shape), "datatype": "UINT8", "data": image.ravel().tolist()},
            {"name": "plan", "shape": list(plans.shape), "datatype": "FP32", "data": plans.ravel().tolist()},
        ],
        **extra,
    }


def _outputs(body: dict) -> dict[str, tuple[list[int], str, np.ndarray]]:
    return {o["name"]: (o["shape"], o["datatype"], np.array(o["data"])) for o in body["outputs"]}


def test_health_and_server_metadata(client):
    assert client.get("/v2/health/live").json() == {"live": True}
    r = client.get("/v2/health/ready")
    assert r.status_code == 200 and r.json() == {"ready": True}
    meta = client.get("/v2").json()
    assert meta["name"] == "firp-service"
    assert meta["extensions"] == ["binary_tensor_data", "model_repository", "statistics", "schedule_policy"]


def test_model_metadata_and_readiness(client):
    version = client.get("/v1/model").json()["version"]
    meta = client.get("/v2/models/tiny").json()
    assert meta["name"] == "tiny" and meta["versions"] == [version]
    assert {(t["name"], t["datatype"]) for t in meta["inputs"]} == {("image", "UINT8"), ("plan", "FP32")}
    shapes = {t["name"]: t["shape"] for t in meta["outputs"]}
    assert shapes["member_scores"] == [-1, 3] and shapes["score"] == [-1]
    assert client.get(f"/v2/models/tiny/versions/{version}").json() == meta
    assert client.get("/v2/models/tiny/ready").json() == {"name": "tiny", "ready": True}
    assert client.get(f"/v2/models/tiny/versions/{version}/ready").json() == {"name": "tiny", "ready": True}
    r = client.get("/v2/models/other")
    assert r.status_code == 404 and r.json()["rule"] == "unknown_model"
    # the protocol's error body: {"error": "<message>"}, the field and the rule beside it
    assert isinstance(r.json()["error"], str) and "'other'" in r.json()["error"]
    for path in ("/v2/models/tiny/versions/000000000000", "/v2/models/tiny/versions/000000000000/ready"):
        r = client.get(path)
        assert r.status_code == 404 and r.json()["field"] == "model_version" and isinstance(r.json()["error"], str)


def test_the_body_may_repeat_the_paths_model_as_kserves_client_sends_it(client):
    version = client.get("/v1/model").json()["version"]
    body = _infer_body(random_image(40, seed=1), valid_plans(1, 9, seed=2))
    r = client.post("/v2/models/tiny/infer", json={**body, "model_name": "tiny", "model_version": version})
    assert r.status_code == 200, r.text
    r = client.post("/v2/models/tiny/infer", json={**body, "model_name": "other"})
    assert r.status_code == 422 and (r.json()["field"], r.json()["rule"]) == ("model_name", "path_mismatch")
    r = client.post(f"/v2/models/tiny/versions/{version}/infer", json={**body, "model_version": "0"})
    assert r.status_code == 422 and (r.json()["field"], r.json()["rule"]) == ("model_version", "path_mismatch")
    r = client.post("/v2/models/tiny/infer", json={**body, "model_version": "0"})
    assert r.status_code == 404 and (r.json()["field"], r.json()["rule"]) == ("model_version", "unknown_version")


def test_infer_round_trip_equals_the_ensemble(client, tiny_bundle):
    image = random_image(40, seed=5)
    plans = valid_plans(3, 11, seed=6)
    r = client.post("/v2/models/tiny/infer", json=_infer_body(image, plans, id="req-9"))
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["model_name"] == "tiny" and body["id"] == "req-9"
    assert body["parameters"]["threshold"] == 0.5 and body["parameters"]["elapsed_ms"] > 0
    out = _outputs(body)
    assert list(out) == ["score", "success", "spread", "member_scores", "failure_step", "attention"]
    want = EnsembleScorer(load_bundle(tiny_bundle)).score(image, plans)
    shape, dtype, score = out["score"]
    assert (shape, dtype) == ([3], "FP32")
    np.testing.assert_allclose(score, want.probabilities, atol=1e-6)  # FP32 on the wire
    assert out["success"][1] == "BOOL" and out["success"][2].tolist() == want.success.tolist()
    assert out["member_scores"][0] == [3, 3]
    np.testing.assert_allclose(out["member_scores"][2].reshape(3, 3), want.member_probabilities.T, atol=1e-6)
    np.testing.assert_allclose(out["spread"][2], want.spread, atol=1e-6)
    assert out["attention"][0] == [3, 11]
    np.testing.assert_allclose(out["attention"][2].reshape(3, 11), want.weights, atol=1e-6)
    assert out["failure_step"][1] == "INT64"
    expected_steps = [-1 if ok else int(np.argmax(w)) for w, ok in zip(want.weights, want.success)]
    assert out["failure_step"][2].tolist() == expected_steps


def test_v1_and_v2_agree(client):
    """The same image (PNG for /v1 and BYTES for V2, raw pixels for V2 UINT8) and plan, the same score."""
    image = random_image(40, seed=8)
    plan = valid_plans(1, 9, seed=9)[0]
    from .helpers import encode_image

    v1 = client.post("/v1/score", json={"image": encode_image(image), "plan": plan.tolist()}).json()
    v2_pixels = _outputs(client.post("/v2/models/tiny/infer", json=_infer_body(image, plan)).json())
    bytes_body = {"inputs": [
        {"name": "plan", "shape": [9, 16], "datatype": "FP64", "data": plan.tolist()},  # nested data is fine too
        {"name": "image", "shape": [1], "datatype": "BYTES", "data": [encode_image(image)]},
    ]}
    v2_png = _outputs(client.post("/v2/models/tiny/infer", json=bytes_body).json())
    assert v1["score"] == pytest.approx(float(v2_pixels["score"][2][0]), abs=1e-6)
    assert v1["score"] == pytest.approx(float(v2_png["score"][2][0]), abs=1e-6)
    assert v2_pixels["score"][0] == [1]  # one plan without the N axis is still N = 1


def test_requested_outputs_only(client):
    body = _infer_body(random_image(40), valid_plans(2, 10), outputs=[{"name": "spread"}, {"name": "score"}])
    r = client.post("/v2/models/tiny/infer", json=body)
    assert [o["name"] for o in r.json()["outputs"]] == ["spread", "score"]


def test_versioned_infer(client):
    version = client.get("/v1/model").json()["version"]
    body = _infer_body(random_image(40), valid_plans(1, 10))
    assert client.post(f"/v2/models/tiny/versions/{version}/infer", json=body).status_code == 200
    assert client.post("/v2/models/tiny/versions/nope/infer", json=body).status_code == 404


IMG = random_image(40)
PLANS = valid_plans(2, 10)


def _with(index: int, **changes) -> dict:
    body = _infer_body(IMG, PLANS)
    body["inputs"][index].update(changes)
    return body


BAD = [
    ("unknown input", {"inputs": _infer_body(IMG, PLANS)["inputs"] + [{"name": "depth", "shape": [1],
                                                                       "datatype": "FP32", "data": [1.0]}]},
     422, "inputs[2].name", "unknown_input"),
    ("image missing", {"inputs": _infer_body(IMG, PLANS)["inputs"][1:]}, 422, "inputs", "missing_input"),
    ("image twice", {"inputs": _infer_body(IMG, PLANS)["inputs"] * 2}, 422, "inputs[2].name", "duplicate_input"),
    ("image as FP32", _with(0, datatype="FP32"), 422, "inputs[0].datatype", "datatype"),
    ("image not H x W x 3", _with(0, shape=[40, 120]), 422, "inputs[0].shape", "shape"),
    ("image shape and data disagree", _with(0, shape=[40, 39, 3]), 422, "inputs[0].data", "shape"),
    ("image values above 255", _with(0, data=[256] * (40 * 40 * 3)), 422, "inputs[0].data", "range"),
    ("image values as floats", _with(0, data=[0.5] * (40 * 40 * 3)), 422, "inputs[0].data", "data"),
    ("image of strings", _with(0, data=["a"] * (40 * 40 * 3)), 422, "inputs[0].data", "data"),
    ("image of objects", _with(0, data=[{"a": 1}] * (40 * 40 * 3)), 422, "inputs[0].data", "data"),
    ("ragged data", _with(0, data=[[1, 2], [3]]), 422, "inputs[0].data", "data"),
    ("huge image declared", _with(0, shape=[100_000, 100_000, 3]), 422, "inputs[0]", "dimensions"),
    ("negative dimension", _with(1, shape=[-2, 10, 16]), 422, "inputs[1].shape", "batch_size"),
    ("BYTES image not base64", _with(0, datatype="BYTES", shape=[1], data=["%%%"]), 422, "inputs[0]", "base64"),
    ("BYTES image of two strings", _with(0, datatype="BYTES", shape=[2], data=[png_b64(), png_b64()]), 422,
     "inputs[0].data", "shape"),
    ("plan as INT64", _with(1, datatype="INT64"), 422, "inputs[1].datatype", "datatype"),
    ("plan 4-D", _with(1, shape=[1, 2, 10, 16]), 422, "inputs[1].shape", "shape"),
    ("plan width 8", _with(1, shape=[2, 20, 8]), 422, "plan[0]", "width"),
    ("plan too long", _with(1, shape=[1, 20, 16]), 422, "plan[0]", "length"),
    ("plan batch above max_batch", {"inputs": _infer_body(IMG, valid_plans(5, 8))["inputs"]}, 422,
     "inputs[1].shape", "batch_size"),
    ("plan with a string", _with(1, data=["x"] + PLANS.ravel().tolist()[1:]), 422, "inputs[1].data", "data"),
    ("plan not one-hot", _with(1, data=[0.0] * PLANS.size), 422, "plan[0][0]", "one_hot"),
    ("unknown output", {**_infer_body(IMG, PLANS), "outputs": [{"name": "logits"}]}, 422, "outputs[0].name",
     "unknown_output"),
    ("no inputs field", {"id": "x"}, 422, "inputs", "missing"),
    ("shape of floats", _with(1, shape=[2.0, 10, 16]), 422, "inputs[1].shape[0]", "int_type"),
]


@pytest.mark.parametrize("case", BAD, ids=[c[0] for c in BAD])
def test_bad_tensors_are_4xx_naming_field_and_rule(client, case):
    _, body, status, field, rule = case
    r = client.post("/v2/models/tiny/infer", json=body)
    assert r.status_code == status, r.text
    assert (r.json()["field"], r.json()["rule"]) == (field, rule), r.json()
