"""Conformance with the Open Inference Protocol's REST API, and KServe's own client against the service.

``open_inference_rest.yaml`` describes the protocol's routes and JSON objects (written from the
protocol's text, not from this service). Every route it lists must exist here for its method, versioned
and unversioned, and every answer -- success and error -- must validate against the protocol's schema
for that status. Then ``kserve.InferenceRESTClient`` (protocol v2; it sends ``model_name`` in the body)
drives a real loopback server: health, readiness, JSON and binary inference, and an error.
"""

from __future__ import annotations

import asyncio
import re
from pathlib import Path

import jsonschema
import numpy as np
import pytest
import yaml

from service.app import create_app
from tests.firp.bundle_helpers import random_image, valid_plans
from tests.loopback import serve_on_loopback

SPEC = yaml.safe_load((Path(__file__).with_name("open_inference_rest.yaml")).read_text())
IMAGE = random_image(40, seed=5)
PLANS = valid_plans(2, 10, seed=6)


def _schema(ref: str) -> dict:
    """A component schema with the document's components beside it, so its $refs resolve."""
    return {"$ref": ref, "components": SPEC["components"]}


def _validate(body: object, operation: dict, status: int) -> None:
    response = operation["responses"][str(status)]
    schema = response["content"]["application/json"]["schema"]
    jsonschema.validate(body, _schema(schema["$ref"]), cls=jsonschema.Draft202012Validator)


def _template(path: str) -> str:
    """A path with its parameters' names dropped: /v2/models/{name} and /v2/models/{model_name} are one route."""
    return re.sub(r"\{[^}]+\}", "{}", path)


def _infer_body(**extra) -> dict:
    return {"inputs": [
        {"name": "image", "shape": list(IMAGE.shape), "datatype": "UINT8", "data": IMAGE.ravel().tolist()},
        {"name": "plan", "shape": list(PLANS.shape), "datatype": "FP32", "data": PLANS.ravel().tolist()},
    ], **extra}


def test_every_route_of_the_protocol_is_served(settings):
    ours = create_app(settings).openapi()["paths"]  # the service's own description of what it serves
    served = {(_template(path), method.upper()) for path, item in ours.items() for method in item}
    wanted = {(_template(path), method.upper()) for path, item in SPEC["paths"].items() for method in item}
    assert len(wanted) == 9 and wanted <= served, sorted(wanted - served)


def test_every_answer_has_the_protocols_shape(client):
    version = client.get("/v1/model").json()["version"]
    values = {"model_name": "tiny", "model_version": version}
    checked = 0
    for path, item in SPEC["paths"].items():
        url = path.format(**values)
        for method, operation in item.items():
            if method == "get":
                r = client.get(url)
            else:
                request = _infer_body(id="conformance-1", outputs=[{"name": "score"}, {"name": "success"}])
                jsonschema.validate(request, _schema(operation["requestBody"]["content"]["application/json"]
                                                     ["schema"]["$ref"]), cls=jsonschema.Draft202012Validator)
                r = client.post(url, json=request)
            assert r.status_code == 200, (url, r.text)
            _validate(r.json(), operation, 200)
            checked += 1
    assert checked == 9
    # the errors the protocol names: an unknown model or version (404), a bad request (4xx)
    for path in ("/v2/models/{model_name}", "/v2/models/{model_name}/versions/{model_version}"):
        r = client.get(path.format(model_name="other", model_version=version))
        assert r.status_code == 404
        _validate(r.json(), SPEC["paths"][path]["get"], 404)
    r = client.get(f"/v2/models/tiny/versions/{'0' * 12}")
    assert r.status_code == 404
    _validate(r.json(), SPEC["paths"]["/v2/models/{model_name}/versions/{model_version}"]["get"], 404)
    bad = _infer_body()
    bad["inputs"][1].update(shape=[2, 10, 15], data=[0.0] * 300)  # 16 columns in the contract
    r = client.post("/v2/models/tiny/infer", json=bad)
    assert 400 <= r.status_code < 500
    error = SPEC["components"]["schemas"]["error_response"]
    jsonschema.validate(r.json(), error)
    assert "16 numbers" in r.json()["error"] and r.json()["field"].startswith("plan")  # ours beside the message


# ------------------------------------------------------------------------------------------------
# KServe's own client over loopback
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def loopback(settings):
    with serve_on_loopback(create_app(settings)) as address:
        yield f"http://{address}"


def test_kserves_rest_client_infers_and_reads_errors(loopback, client):
    """``kserve.InferenceRESTClient`` with protocol v2, unchanged: health, model readiness, inference with
    JSON tensors and with binary ones, outputs equal to /v1's, and a refused request's message."""
    import httpx
    from kserve import InferenceRESTClient, InferInput, InferRequest, RESTConfig  # a dev dependency

    v1 = [client.post("/v1/score", json={"image": _png(IMAGE), "plan": p.astype(np.float32).tolist()}).json()
          for p in PLANS]

    async def drive() -> tuple:
        kserve = InferenceRESTClient(RESTConfig(protocol="v2", timeout=60))
        try:
            assert await kserve.is_server_live(loopback) and await kserve.is_server_ready(loopback)
            assert await kserve.is_model_ready(loopback, "tiny")
            assert not await kserve.is_model_ready(loopback, "other")
            answers = []
            for binary in (False, True):
                image = InferInput("image", list(IMAGE.shape), "UINT8")
                image.set_data_from_numpy(IMAGE, binary_data=binary)
                plan = InferInput("plan", list(PLANS.shape), "FP32")
                plan.set_data_from_numpy(PLANS.astype(np.float32), binary_data=binary)
                request = InferRequest(model_name="tiny", infer_inputs=[image, plan], request_id=f"kserve-{binary}")
                answers.append(await kserve.infer(loopback, request, model_name="tiny"))
            bad = InferInput("plan", [2, 10, 15], "FP32")
            bad.set_data_from_numpy(np.zeros((2, 10, 15), np.float32), binary_data=False)
            image = InferInput("image", list(IMAGE.shape), "UINT8")
            image.set_data_from_numpy(IMAGE, binary_data=False)
            with pytest.raises(httpx.HTTPStatusError) as refused:
                await kserve.infer(loopback, InferRequest(model_name="tiny", infer_inputs=[image, bad]),
                                   model_name="tiny")
            return answers, refused.value
        finally:
            await kserve.close()

    answers, refused = asyncio.run(drive())
    for answer in answers:
        outputs = {o.name: o for o in answer.outputs}
        np.testing.assert_allclose(outputs["score"].as_numpy(), [r["score"] for r in v1], atol=1e-6)
        np.testing.assert_array_equal(outputs["success"].as_numpy(), [r["success"] for r in v1])
        assert answer.model_name == "tiny"
    assert [a.id for a in answers] == ["kserve-False", "kserve-True"]
    assert refused.response.status_code == 422 and "16 numbers" in str(refused)  # the protocol's error string


def _png(image: np.ndarray) -> str:
    from .helpers import encode_image

    return encode_image(image)
