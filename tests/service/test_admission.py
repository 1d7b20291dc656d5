"""Admission control: overload is refused with 503 + Retry-After, expired work is dropped with 504.

The model's pass is held by a gate (a threading.Event the worker thread waits on), so every test
builds its overload deterministically: which requests are in the pass, which are queued, which are
refused -- no sleeps to hope a queue formed.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import Future
from functools import partial

import pytest

from service.app import create_app
from service.settings import ServiceSettings
from tests.firp.bundle_helpers import random_image, valid_plans

from .conftest import STRICT
from .helpers import ServiceClient, encode_image

IMAGE = encode_image(random_image(40))


class Gate:
    """Holds every forward pass until opened; records the plans of each pass."""

    def __init__(self, app):
        self.model = app.state.model
        self.real = self.model.score_jobs
        self.entered = threading.Event()
        self.open = threading.Event()
        self.passes: list[int] = []
        self.model.score_jobs = self._gated

    def _gated(self, jobs):
        self.passes.append(sum(len(j.plans) for j in jobs))
        self.entered.set()
        assert self.open.wait(30), "the test never opened the gate"
        return self.real(jobs)


def _send(c: ServiceClient, url: str, body: dict, headers: dict | None = None) -> Future:
    return c.portal.start_task_soon(partial(c.client.post, url, json=body, headers=headers or {}))


def _single(seed: int = 0) -> dict:
    return {"image": IMAGE, "plan": valid_plans(1, 9, seed=seed)[0].tolist()}


def _batch(n: int, seed: int = 0) -> dict:
    return {"image": IMAGE, "plans": valid_plans(n, 9, seed=seed).tolist()}


def _until(condition, what: str, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.002)


def _metric(c: ServiceClient, sample: str) -> float:
    for line in c.get("/metrics").text.splitlines():
        if line.startswith(sample + " "):
            return float(line.split()[-1])
    return 0.0


def _app(tiny_bundle, **settings):
    return create_app(ServiceSettings(bundle=tiny_bundle, **{**STRICT, **settings}))


def test_requests_beyond_the_concurrency_bound_get_503_and_health_is_never_shed(tiny_bundle):
    app = _app(tiny_bundle, max_concurrent_requests=2)
    with ServiceClient(app) as c:
        gate = Gate(app)
        held = [_send(c, "/v1/score", _single(s)) for s in range(2)]
        _until(lambda: app.state.in_flight.count == 2, "two admitted requests")
        refused = c.post("/v1/score", json=_single(5))
        v2 = c.post("/v2/models/tiny/infer", json={"inputs": []})  # refused before its body is read
        operations = [c.get(path).status_code for path in ("/healthz", "/readyz", "/v2/health/ready", "/metrics",
                                                           "/v1/model")]
        gate.open.set()
        answers = [f.result(30) for f in held]
        shed = _metric(c, 'firp_shed_requests_total{reason="concurrency"}')
        after = c.post("/v1/score", json=_single(6))
    assert refused.status_code == 503 and refused.headers["Retry-After"] == "1"
    assert refused.json()["error"]["rule"] == "overloaded" and "max_concurrent_requests" in refused.json()["error"]["message"]
    assert v2.status_code == 503 and v2.json()["rule"] == "overloaded" and isinstance(v2.json()["error"], str)
    assert operations == [200] * 5
    assert [a.status_code for a in answers] == [200, 200] and after.status_code == 200
    assert shed == 2


def test_plans_beyond_the_queue_bound_get_503(tiny_bundle):
    app = _app(tiny_bundle, max_queued_plans=4, retry_after_s=3)
    with ServiceClient(app) as c:
        gate = Gate(app)
        first = _send(c, "/v1/score", _single())
        assert gate.entered.wait(10)  # the first request is in the (held) pass, nothing is queued
        queued = [_send(c, "/v1/score/batch", _batch(3)), _send(c, "/v1/score", _single(1))]
        _until(lambda: app.state.batcher.queued_plans == 4, "four queued plans")
        refused = c.post("/v1/score", json=_single(2))
        gate.open.set()
        answers = [f.result(30) for f in (first, *queued)]
        shed = _metric(c, 'firp_shed_requests_total{reason="queue"}')
    assert refused.status_code == 503 and refused.headers["Retry-After"] == "3"
    assert refused.json()["error"]["rule"] == "overloaded" and "max_queued_plans" in refused.json()["error"]["message"]
    assert [a.status_code for a in answers] == [200, 200, 200] and shed == 1
    assert gate.passes == [1, 4]  # the refused plan was never computed


def test_work_whose_budget_runs_out_in_the_queue_is_answered_504_and_never_computed(tiny_bundle):
    app = _app(tiny_bundle)
    with ServiceClient(app) as c:
        gate = Gate(app)
        first = _send(c, "/v1/score", _single())
        assert gate.entered.wait(10)
        start = time.monotonic()
        late = c.post("/v1/score/batch", json=_batch(3, seed=1), headers={"X-Request-Timeout": "0.2"})
        waited = time.monotonic() - start
        v2_late = c.post("/v2/models/tiny/infer", json={
            "parameters": {"timeout": 150_000},  # microseconds
            "inputs": [{"name": "image", "shape": [1], "datatype": "BYTES", "data": [IMAGE]},
                       {"name": "plan", "shape": [9, 16], "datatype": "FP32",
                        "data": [x for row in valid_plans(1, 9, seed=2)[0].tolist() for x in row]}]})
        on_time = _send(c, "/v1/score", _single(3), headers={"X-Request-Timeout": "30"})
        gate.open.set()
        answers = [f.result(30) for f in (first, on_time)]
        dropped = _metric(c, 'firp_deadline_exceeded_total{stage="queued"}')
    assert late.status_code == 504 and late.json()["error"]["rule"] == "deadline_exceeded"
    assert v2_late.status_code == 504 and v2_late.json()["rule"] == "deadline_exceeded"  # the V2 error shape
    assert 0.2 <= waited < 5.0
    assert [a.status_code for a in answers] == [200, 200] and dropped == 2
    assert gate.passes == [1, 1]  # the expired plans never reached a pass


def test_the_default_budget_holds_without_micro_batching(tiny_bundle):
    app = _app(tiny_bundle, micro_batch=False, request_timeout_s=0.2)
    with ServiceClient(app) as c:
        gate = Gate(app)
        first = _send(c, "/v1/score", _single(), headers={"X-Request-Timeout": "30"})
        assert gate.entered.wait(10)
        late = _send(c, "/v1/score", _single(1))  # waits for the inference token past its 0.2 s
        time.sleep(0.4)
        gate.open.set()
        answers = [f.result(30) for f in (first, late)]
    assert answers[0].status_code == 200
    assert answers[1].status_code == 504 and answers[1].json()["error"]["rule"] == "deadline_exceeded"
    assert gate.passes == [1]


@pytest.mark.parametrize("value", ["abc", "0", "-1", "nan", "inf", "3601"])
def test_a_malformed_timeout_header_is_refused_naming_it(client, value):
    answer = client.post("/v1/score", json=_single(), headers={"X-Request-Timeout": value})
    assert answer.status_code == 400
    assert answer.json()["error"]["field"] == "X-Request-Timeout" and answer.json()["error"]["rule"] == "timeout"


@pytest.mark.parametrize("value", [-1, 1.5, "100", True, 10**13])
def test_a_malformed_v2_timeout_parameter_is_refused_naming_it(client, value):
    answer = client.post("/v2/models/tiny/infer", json={
        "parameters": {"timeout": value},
        "inputs": [{"name": "image", "shape": [1], "datatype": "BYTES", "data": [IMAGE]},
                   {"name": "plan", "shape": [9, 16], "datatype": "FP32",
                    "data": [x for row in valid_plans(1, 9)[0].tolist() for x in row]}]})
    assert answer.status_code == 422
    assert answer.json()["field"] == "parameters.timeout" and answer.json()["rule"] == "timeout"


def test_settings_refuse_a_queue_smaller_than_one_batch(tiny_bundle):
    with pytest.raises(ValueError, match="max_queued_plans 2 < max_batch 4"):
        ServiceSettings(bundle=tiny_bundle, **{**STRICT, "max_queued_plans": 2})


def test_a_queue_longer_than_its_wait_bound_refuses_at_the_door(tiny_bundle):
    """The measured cost of a plan times the queued plans: beyond max_queue_wait_s, a request is
    refused before its body is read -- even an invalid body gets the 503, not a 422."""
    app = _app(tiny_bundle, max_queue_wait_s=0.5)
    with ServiceClient(app) as c:
        gate = Gate(app)
        first = _send(c, "/v1/score", _single())
        assert gate.entered.wait(10)
        queued = _send(c, "/v1/score", _single(1))
        _until(lambda: app.state.batcher.queued_plans == 1, "one queued plan")
        app.state.batcher.seconds_per_plan = 0.4  # as if measured: 0.4 s of work waits
        second = c.post("/v1/score", json=_single(2))  # 0.8 s expected: refused by the batcher
        app.state.batcher.seconds_per_plan = 0.6
        door = c.post("/v1/score", json={"not": "a valid body"})  # 0.6 s waits already: refused unread
        gate.open.set()
        answers = [f.result(30) for f in (first, queued)]
    for refused in (second, door):
        assert refused.status_code == 503 and refused.json()["error"]["rule"] == "overloaded", refused.text
        assert "max_queue_wait_s" in refused.json()["error"]["message"]
    assert [a.status_code for a in answers] == [200, 200]


def test_admission_reserves_the_plans_a_request_is_expected_to_bring():
    """A burst is admitted only as far as the bounds allow *with* the requests still being read: each
    admitted request reserves the plans requests have been bringing, until its submit or its end."""
    from service.batching import MicroBatcher

    batcher = MicroBatcher(model=None, max_plans=64, max_queued_plans=8)  # admission never touches the model
    batcher.plans_per_request = 4.0
    assert batcher.admit() is None and batcher.reserved == 1  # a lone request: always
    assert batcher.admit() is None and batcher.reserved_plans == 8  # 4 reserved + 4 expected = 8 <= 8
    refused = batcher.admit()
    assert refused is not None and "2 requests are being read" in refused and "max_queued_plans" in refused
    assert batcher.reserved == 2  # a refusal reserves nothing
    batcher.release()
    batcher.release()
    assert batcher.reserved == 0 and batcher.admit() is None

    timed = MicroBatcher(model=None, max_plans=64, max_queue_wait_s=0.05)
    timed.plans_per_request, timed.seconds_per_plan = 2.0, 0.01
    assert timed.admit() is None and timed.admit() is None  # (0 + 2 + 2) plans x 10 ms = 0.04 s
    refused = timed.admit()  # (0 + 4 + 2) x 10 ms = 0.06 s > 0.05 s
    assert refused is not None and "max_queue_wait_s" in refused and "about 0.06 s of work" in refused


def test_every_admitted_request_releases_its_reservation(tiny_bundle):
    """Answered, refused by validation (422) or by a bad header: no reservation outlives its request."""
    app = _app(tiny_bundle)
    with ServiceClient(app) as c:
        answers = [c.post("/v1/score", json=_single(1)).status_code,
                   c.post("/v1/score/batch", json=_batch(3)).status_code,
                   c.post("/v1/score", json={"image": IMAGE, "plan": [[0.0] * 15] * 9}).status_code,
                   c.post("/v1/score", json={"not": "a body"}).status_code,
                   c.post("/v2/models/tiny/infer", json={"inputs": []}).status_code]
        batcher = app.state.batcher
        assert (batcher.reserved, batcher.queued_plans) == (0, 0)
    assert answers == [200, 200, 422, 422, 422]
    assert 1.0 < batcher.plans_per_request < 3.0  # moved towards what the answered requests brought
