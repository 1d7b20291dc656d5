"""The world API's bounded queue, deadlines and drain, on a scripted world whose executions wait for
the test (a threading.Event): which calls run, which wait, which are refused is built, not timed.
This world stands for no simulator; the sim worker's and robosuite worker's own tests run theirs."""

from __future__ import annotations

import threading
import time
from concurrent.futures import Future
from functools import partial

import numpy as np
import pytest

from tests.firp.bundle_helpers import valid_plans
from tests.service.helpers import ServiceClient
from world_api.app import create_world_app
from world_api.backend import EpisodeStart, Outcome
from world_api.settings import WorldSettings

PLAN = valid_plans(1, 8)[0]


class GatedWorld:
    name = "gated_world"
    tasks = ("task",)
    outcome_kinds = ("success",)
    image_size = 16

    def __init__(self) -> None:
        self.open = threading.Event()
        self.running = threading.Event()
        self.executed: list[int] = []

    def warm_up(self) -> None:
        pass

    def begin(self, task: str, seed: int, pose_error_mm: float, pose_error_deg: float) -> EpisodeStart:
        return EpisodeStart(task, seed, {"blocks": {}, "scene": {}}, np.zeros((16, 16, 3), np.uint8), np.zeros(9))

    def execute(self, start: EpisodeStart, plan: np.ndarray, record_frames: bool) -> Outcome:
        self.running.set()
        assert self.open.wait(30), "the test never opened the gate"
        self.executed.append(start.seed)
        return Outcome(True, "success", "done", {}, 1.0, False)

    def close(self) -> None:
        pass


@pytest.fixture()
def world():
    return GatedWorld()


def _client(world: GatedWorld, **settings) -> ServiceClient:
    return ServiceClient(create_world_app(world, WorldSettings(**settings)))


def _ready(c: ServiceClient) -> None:
    deadline = time.monotonic() + 10
    while c.get("/readyz").status_code != 200:
        assert time.monotonic() < deadline
        time.sleep(0.01)


def _execute(c: ServiceClient, episode: str, headers: dict | None = None) -> Future:
    return c.portal.start_task_soon(partial(c.client.post, f"/v1/episodes/{episode}/execute",
                                            json={"plan": PLAN.tolist()}, headers=headers or {}))


def _episodes(c: ServiceClient, n: int) -> list[str]:
    return [c.post("/v1/episodes", json={"task": "task", "seed": s}).json()["episode_id"] for s in range(n)]


def test_calls_beyond_the_queue_get_503_with_retry_after(world):
    with _client(world, max_queued=2) as c:
        _ready(c)
        a, b, extra = _episodes(c, 3)
        running = _execute(c, a)
        assert world.running.wait(10)
        waiting = _execute(c, b)
        deadline = time.monotonic() + 10
        while c.app.state.sim.runner.pending < 2:
            assert time.monotonic() < deadline
            time.sleep(0.005)
        refused = c.post(f"/v1/episodes/{extra}/execute", json={"plan": PLAN.tolist()})
        also = c.post("/v1/episodes", json={"task": "task", "seed": 9})
        world.open.set()
        answers = [f.result(30) for f in (running, waiting)]
    for r in (refused, also):
        assert r.status_code == 503 and r.headers["Retry-After"] == "1" and r.json()["error"]["rule"] == "overloaded"
    assert [r.status_code for r in answers] == [200, 200] and world.executed == [0, 1]


def test_a_call_whose_budget_ends_in_the_queue_is_never_run(world):
    with _client(world) as c:
        _ready(c)
        a, b = _episodes(c, 2)
        running = _execute(c, a)
        assert world.running.wait(10)
        late = _execute(c, b, headers={"X-Request-Timeout": "0.1"})
        time.sleep(0.3)
        world.open.set()
        answers = [f.result(30) for f in (running, late)]
        bad = c.post(f"/v1/episodes/{a}/execute", json={"plan": PLAN.tolist()}, headers={"X-Request-Timeout": "-2"})
    assert answers[0].status_code == 200
    assert answers[1].status_code == 504 and answers[1].json()["error"]["rule"] == "deadline_exceeded"
    assert world.executed == [0]  # the expired execution never ran
    assert bad.status_code == 400 and bad.json()["error"]["field"] == "X-Request-Timeout"


def test_draining_refuses_new_work_and_readiness_says_so(world):
    world.open.set()
    with _client(world) as c:
        _ready(c)
        (a,) = _episodes(c, 1)
        c.app.state.sim.draining = True  # what SIGTERM does (firp.core.draining)
        ready = c.get("/readyz")
        refused = c.post(f"/v1/episodes/{a}/execute", json={"plan": PLAN.tolist()})
    assert ready.status_code == 503 and ready.json()["error"]["rule"] == "draining"
    assert refused.status_code == 503 and refused.json()["error"]["rule"] == "not_ready"
