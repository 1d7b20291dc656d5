"""Micro-batching: concurrent requests share forward passes, each gets its own scores and errors."""

from __future__ import annotations

import threading
import time
from typing import Any

import anyio
import httpx
import numpy as np
import pytest

from firp.bundle import load_bundle
from firp.serving import EnsembleScorer
from service.app import create_app
from service.settings import ServiceSettings
from tests.firp.bundle_helpers import random_image, valid_plans

from .conftest import STRICT
from .helpers import ServiceClient, encode_image


def _concurrently(c: ServiceClient, requests: list[tuple[str, dict[str, Any]]]) -> list[httpx.Response]:
    """Send every request at once (one task each on the app's event loop); answers in order."""
    answers: list[httpx.Response | None] = [None] * len(requests)

    async def send_all() -> None:
        async def one(i: int) -> None:
            url, body = requests[i]
            answers[i] = await c.client.post(url, json=body)

        async with anyio.create_task_group() as tg:
            for i in range(len(requests)):
                tg.start_soon(one, i)

    c.portal.call(send_all)
    return answers  # type: ignore[return-value]


def _gated_passes(app, requests: int) -> list[int]:
    """Hold the first pass until all ``requests`` are either in it or waiting in the batcher's queue,
    so those left over must share the passes after it (no sleep: the gate opens on the queue's own
    count). Returns the number of plans of each pass, in order."""
    model, batcher = app.state.model, app.state.batcher
    real, passes = model.score_jobs, []
    opened = threading.Event()

    def gated(jobs):
        if not opened.is_set():
            # the worker thread polls the queue's counter, the event loop keeps queueing requests
            deadline = time.monotonic() + 60
            while len(jobs) + batcher.waiting < requests:
                assert time.monotonic() < deadline, f"only {len(jobs) + batcher.waiting} of {requests} requests arrived"
                opened.wait(0.002)
            opened.set()
        passes.append(sum(len(j.plans) for j in jobs))
        return real(jobs)

    model.score_jobs = gated
    return passes


def test_concurrent_requests_share_passes_and_get_their_own_answers(tiny_bundle):
    app = create_app(ServiceSettings(bundle=tiny_bundle, **STRICT))
    images = [random_image(40, seed=s) for s in range(3)]
    plans = [valid_plans(1, t, seed=10 + t)[0] for t in (8, 9, 12, 9, 8, 16)]
    bad = valid_plans(1, 9, seed=99)[0]
    bad[4, :7] = 1.0  # every category hot
    requests = [("/v1/score", {"image": encode_image(images[i % 3]), "plan": p.tolist()}) for i, p in enumerate(plans)]
    requests.insert(3, ("/v1/score", {"image": encode_image(images[0]), "plan": bad.tolist()}))
    requests.append(("/v1/score/batch", {"image": encode_image(images[1]), "plans": [p.tolist() for p in plans[:2]]}))
    requests.append(("/v1/score", {"image": "%%%", "plan": plans[0].tolist()}))  # a bad image fails alone too
    with ServiceClient(app) as c:
        passes = _gated_passes(app, requests=len(requests))
        answers = _concurrently(c, requests)
        metrics = c.get("/metrics").text
    scorer = EnsembleScorer(load_bundle(tiny_bundle))
    good = [i for i in range(len(requests)) if i not in (3, len(requests) - 1)]
    for i in good:
        assert answers[i].status_code == 200, answers[i].text
    singles = [i for i in good if requests[i][0] == "/v1/score"]
    for k, i in enumerate(singles):
        want = scorer.score(images[k % 3], plans[k][None])
        got = answers[i].json()
        assert got["score"] == pytest.approx(float(want.probabilities[0]), abs=1e-6)
        np.testing.assert_allclose(got["attention"], want.weights[0], atol=1e-6)
    batch = answers[len(requests) - 2].json()["results"]
    for p, r in zip(plans[:2], batch):
        assert r["score"] == pytest.approx(float(scorer.score(images[1], p[None]).probabilities[0]), abs=1e-6)
    assert answers[3].status_code == 422 and answers[3].json()["error"]["field"] == "plan[4]"
    assert answers[-1].status_code == 422 and answers[-1].json()["error"]["rule"] == "base64"
    # nine requests (ten plans): the first pass took what had arrived, the rest queued behind it and
    # shared the second pass (32 plans fit in one)
    assert sum(passes) == 6 + 1 + 2 + 1 and len(passes) <= 2
    count = float(metrics.split("firp_micro_batch_requests_count ")[1].split()[0])
    assert count == len(passes)


def test_a_pass_holds_at_most_max_plans(tiny_bundle):
    app = create_app(ServiceSettings(bundle=tiny_bundle, micro_batch_max_plans=3, **STRICT))
    image = encode_image(random_image(40))
    requests = [("/v1/score/batch", {"image": image, "plans": valid_plans(2, 8, seed=s).tolist()}) for s in range(5)]
    with ServiceClient(app) as c:
        passes = _gated_passes(app, requests=len(requests))
        answers = _concurrently(c, requests)
    assert all(a.status_code == 200 for a in answers)
    assert passes == [2] * 5  # 2-plan requests never pair up under a 3-plan cap


def test_a_lone_request_is_not_held_back(tiny_bundle):
    """No batching window: with one job queued, the next batch is that job, taken without waiting for
    company (were the scoring thread to wait for a second job, this would hang until the guard below)."""
    from concurrent.futures import ThreadPoolExecutor

    from service.batching import MicroBatcher, _Pending
    from service.scorer import ScoreJob

    batcher = MicroBatcher(model=None, max_plans=32)  # type: ignore[arg-type]  # _next_batch never scores
    lone = _Pending(ScoreJob(b"k", lambda: random_image(40), [valid_plans(1, 8)[0]], ["plan"]))
    batcher._queue.append(lone)
    with ThreadPoolExecutor(1) as pool:  # on a thread of its own, as the scoring thread calls it
        assert pool.submit(batcher._next_batch).result(timeout=30) == [lone]  # a hang guard, not a speed bound
    assert lone.taken and lone.job.timeline.taken_ns is not None


def test_micro_batching_can_be_switched_off(tiny_bundle):
    app = create_app(ServiceSettings(bundle=tiny_bundle, micro_batch=False, **STRICT))
    image = random_image(40)
    plan = valid_plans(1, 10)[0]
    with ServiceClient(app) as c:
        assert app.state.batcher is None
        answers = _concurrently(c, [("/v1/score", {"image": encode_image(image), "plan": plan.tolist()})] * 3)
        assert "firp_micro_batch_requests_count 0.0" in c.get("/metrics").text
    want = EnsembleScorer(load_bundle(tiny_bundle)).score(image, plan[None]).probabilities[0]
    for a in answers:
        assert a.json()["score"] == pytest.approx(float(want), abs=1e-6)


def test_requests_after_stopping_get_503(tiny_bundle):
    app = create_app(ServiceSettings(bundle=tiny_bundle, **STRICT))
    with ServiceClient(app):
        batcher = app.state.batcher
    from service.scorer import ScoreJob

    with pytest.raises(Exception) as info:
        anyio.run(batcher.submit, ScoreJob(b"k", lambda: random_image(40), [valid_plans(1, 8)[0]], ["plan"]))
    assert getattr(info.value, "status", None) == 503
