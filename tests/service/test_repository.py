"""Hot swap through the V2 model repository extension: under load, no request fails, and every
answer names the version that scored it, with that version's scores."""

from __future__ import annotations

import shutil
import time

import anyio
import pytest
import torch

from firp.bundle import load_bundle
from firp.serving import EnsembleScorer
from service.app import create_app
from service.settings import ServiceSettings
from tests.firp.bundle_helpers import export_tiny, random_image, valid_plans

from .conftest import STRICT
from .helpers import ServiceClient, encode_image


@pytest.fixture(scope="module")
def second_bundle(tmp_path_factory):
    """The same model name and task as the tiny bundle, other weights: another version."""
    torch.manual_seed(1)
    return export_tiny(tmp_path_factory.mktemp("swap") / "tiny")


def _version(c: ServiceClient) -> str:
    return c.get("/v1/model").json()["version"]


def test_a_swap_under_load_fails_no_request_and_answers_name_the_scoring_version(tiny_bundle, second_bundle):
    image = random_image(40, seed=3)
    plan = valid_plans(1, 9, seed=4)[0]
    body = {"image": encode_image(image), "plan": plan.tolist()}
    expected = {}
    for bundle in (tiny_bundle, second_bundle):
        expected[bundle] = float(EnsembleScorer(load_bundle(bundle)).score(image, plan[None]).probabilities[0])
    assert expected[tiny_bundle] != pytest.approx(expected[second_bundle], abs=1e-6)
    # The subject is the swap, not admission: with the default bound on the expected wait (0.1 s),
    # eight clients on a busy two-core machine are shed (503 overloaded) whenever the load's thread
    # slows a pass, which is admission doing its job (tests/service/test_admission.py), not a swap failing.
    app = create_app(ServiceSettings(bundle=tiny_bundle, max_queue_wait_s=0.0, **STRICT))
    answers: list[tuple[int, str | None, float | None]] = []
    refusals: list[dict] = []
    with ServiceClient(app) as c:
        old = _version(c)

        async def load_and_swap() -> dict:
            stop = anyio.Event()

            async def client() -> None:
                while not stop.is_set():
                    r = await c.client.post("/v1/score", json=body)
                    ok, payload = r.status_code == 200, r.json()
                    if not ok:
                        refusals.append(payload)
                    answers.append((r.status_code, payload["model"]["version"] if ok else None,
                                    payload["score"] if ok else None))

            async with anyio.create_task_group() as tg:
                for _ in range(8):
                    tg.start_soon(client)
                await anyio.sleep(0.3)
                started = time.monotonic()
                r = await c.client.post("/v2/repository/models/tiny/load",
                                        json={"parameters": {"bundle": str(second_bundle)}})
                loaded = time.monotonic() - started
                await anyio.sleep(0.3)
                stop.set()
            return {"status": r.status_code, "body": r.json(), "seconds": loaded}

        swap = c.portal.call(load_and_swap)
        new = _version(c)
        index = c.post("/v2/repository/index").json()
        metrics = c.get("/metrics").text
        v2_meta = c.get("/v2/models/tiny").json()
    assert swap["status"] == 200 and swap["body"]["version"] == new != old, swap
    assert all(status == 200 for status, _, _ in answers), refusals[:3]
    versions = [v for _, v, _ in answers]
    assert versions[0] == old and versions[-1] == new and set(versions) == {old, new}
    for _, version, score in answers:  # each answer's score is the scoring version's
        assert score == pytest.approx(expected[tiny_bundle if version == old else second_bundle], abs=1e-6)
    assert index == [{"name": "tiny", "version": new, "state": "READY", "reason": ""}]
    assert v2_meta["versions"] == [new]
    assert f'firp_model_info{{name="tiny",task="stacking",version="{new}"}} 1.0' in metrics
    assert f'firp_model_info{{name="tiny",task="stacking",version="{old}"}} 0.0' in metrics


def test_a_bad_bundle_is_refused_and_the_old_one_keeps_serving(tiny_bundle, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(tiny_bundle, broken)
    weights = next(broken.rglob("*.safetensors"))
    weights.write_bytes(weights.read_bytes()[:-8] + b"\0" * 8)  # its sha256 no longer matches the manifest
    app = create_app(ServiceSettings(bundle=tiny_bundle, **STRICT))
    with ServiceClient(app) as c:
        before = _version(c)
        r = c.post("/v2/repository/models/tiny/load", json={"parameters": {"bundle": str(broken)}})
        missing = c.post("/v2/repository/models/tiny/load", json={"parameters": {"bundle": str(tmp_path / "none")}})
        wrong_name = c.post("/v2/repository/models/other/load", json={"parameters": {"bundle": str(tiny_bundle)}})
        unknown = c.post("/v2/repository/models/tiny/load", json={"parameters": {"path": "x"}})
        after = _version(c)
        score = c.post("/v1/score", json={"image": encode_image(random_image(40)), "plan": valid_plans(1, 9)[0].tolist()})
    assert r.status_code == 422 and (r.json()["field"], r.json()["rule"]) == ("parameters.bundle", "sha256")
    assert "the model in use is unchanged" in r.json()["error"]
    assert missing.status_code == 422 and missing.json()["rule"] == "missing"
    assert wrong_name.status_code == 422 and wrong_name.json()["rule"] == "name_mismatch"
    assert unknown.status_code == 422 and unknown.json()["field"] == "parameters.path"
    assert before == after and score.status_code == 200


def test_unload_then_load_the_configured_bundle(tiny_bundle):
    app = create_app(ServiceSettings(bundle=tiny_bundle, **STRICT))
    with ServiceClient(app) as c:
        version = _version(c)
        assert c.post("/v2/repository/models/other/unload").status_code == 404
        r = c.post("/v2/repository/models/tiny/unload")
        assert r.status_code == 200 and r.json()["state"] == "UNAVAILABLE"
        ready = c.get("/readyz")
        score = c.post("/v1/score", json={"image": encode_image(random_image(40)), "plan": valid_plans(1, 9)[0].tolist()})
        index = c.post("/v2/repository/index", json={}).json()
        only_ready = c.post("/v2/repository/index", json={"ready": True}).json()
        load = c.post("/v2/repository/models/tiny/load")  # no body: the configured bundle
        after = c.get("/readyz")
    assert ready.status_code == 503 and ready.json()["status"] == "unloaded"
    assert score.status_code == 503 and score.json()["error"]["rule"] == "not_ready"
    assert index == [{"name": "tiny", "version": version, "state": "UNAVAILABLE", "reason": "unloaded"}]
    assert only_ready == []
    assert load.status_code == 200 and load.json()["version"] == version
    assert after.status_code == 200 and after.json()["status"] == "ready"


def test_the_repository_is_behind_the_api_key(tiny_bundle):
    app = create_app(ServiceSettings(bundle=tiny_bundle, api_key="s3cret", **STRICT))
    with ServiceClient(app) as c:
        assert c.post("/v2/repository/index").status_code == 401
        assert c.post("/v2/repository/models/tiny/unload").status_code == 401
        assert c.post("/v2/repository/index", headers={"X-API-Key": "s3cret"}).status_code == 200


def test_repository_bodies_are_checked(client):
    for body, field, rule in (({"ready": 1}, "ready", "bool_type"), ({"other": True}, "other", "extra_forbidden")):
        r = client.post("/v2/repository/index", json=body)
        assert r.status_code == 422 and (r.json()["field"], r.json()["rule"]) == (field, rule), r.json()
    r = client.post("/v2/repository/index", content=b"{nope", headers={"content-type": "application/json"})
    assert r.status_code == 422 and (r.json()["field"], r.json()["rule"]) == ("body", "json_invalid")
