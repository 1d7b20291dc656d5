"""The HTTP clients: SimClient against a real sim worker on loopback, and the retry/backoff rules of
both clients against a scripted loopback stub (transport tests: the stub stands for no service)."""

from __future__ import annotations


import numpy as np
import pytest

from firp.core.contract import PlanValidationError
from planner_client.backend import SimBackend
from planner_client.clients import ScoreClient, SimClient
from planner_client.embedded import EmbeddedSim
from planner_client.loop import RunConfig, read_records, run_trials
from planner_client.tamp import PlannerConfig, TampPlanner
from planner_client.transport import RequestRejected, RetryPolicy, ServiceUnavailable, request_id

from .conftest import refusing_socket

T = 16
FAST = RetryPolicy(attempts=4, base_delay=0.05, max_delay=1.0)


@pytest.fixture(scope="module")
def planner() -> TampPlanner:
    return TampPlanner(PlannerConfig(horizon=T))


@pytest.fixture
def sim(launcher):
    with SimClient(launcher.sim_url, retry=FAST) as client:
        yield client


# -- SimClient against the real sim worker ----------------------------------------------------------
@pytest.mark.slow
def test_remote_and_embedded_backends_give_the_same_episode_and_label(sim, planner):
    embedded = EmbeddedSim()
    try:
        assert isinstance(sim, SimBackend) and isinstance(embedded, SimBackend)
        remote_ep, local_ep = sim.start("stacking", 21), embedded.start("stacking", 21)
        assert remote_ep.observation == local_ep.observation
        assert remote_ep.image_b64 == local_ep.image_b64 and remote_ep.image_size == (84, 84)
        plan = planner.plan("stacking", remote_ep.observation).actions
        remote, local = sim.execute(remote_ep, plan), embedded.execute(local_ep, plan)
        assert (remote.success, remote.reason, remote.kind) == (local.success, local.reason, local.kind)
        assert remote.sim_seconds == pytest.approx(local.sim_seconds)
        assert remote.frames_b64 is None and remote.unstable is False
    finally:
        embedded.close()


def test_re_execution_gives_the_same_label_and_frames_on_request(sim, planner):
    episode = sim.start("replacement", 22)
    plan = planner.plan("replacement", episode.observation).actions
    first, second = sim.execute(episode, plan), sim.execute(episode, plan, record_frames=True)
    assert (first.success, first.reason, first.final_blocks) == (second.success, second.reason, second.final_blocks)
    assert len(second.frames_b64) == T and second.frames_b64[0] == episode.image_b64


def test_a_forgotten_episode_is_recreated_identically(sim, planner):
    """Deleted on the worker (as after a worker restart or expiry): execute starts it again."""
    episode = sim.start("stacking", 23)
    plan = planner.plan("stacking", episode.observation).actions
    before = sim.execute(episode, plan)
    old_id = episode.episode_id
    sim.delete(episode)
    after = sim.execute(episode, plan)
    assert episode.episode_id != old_id
    assert (after.success, after.reason, after.final_blocks) == (before.success, before.reason, before.final_blocks)


def test_rejections_carry_field_and_rule_and_are_not_retried(sim):
    with pytest.raises(RequestRejected) as err:
        sim.start("juggling", 1)
    assert (err.value.status, err.value.field, err.value.rule) == (422, "task", "unknown_task")
    assert sim.base_url in str(err.value)
    episode = sim.start("stacking", 1)
    with pytest.raises(RequestRejected) as err:
        sim.execute(episode, np.zeros((T, 15)))
    assert (err.value.field, err.value.rule) == ("plan", "width")


def test_the_trial_loop_runs_over_http(sim, planner, tmp_path):
    records = list(run_trials(RunConfig(trials=1, max_iterations=2, out=tmp_path / "run.jsonl"), sim, planner))
    assert len(records) == 1 and records[0]["tamp_success"] in (True, False)
    assert read_records(tmp_path / "run.jsonl") == records


# -- retry and backoff (transport tests against the loopback stub) ----------------------------------
SCORE = {"score": 0.8, "success": True, "threshold": 0.5, "member_scores": [0.8], "spread": 0.0,
         "failure_step": None, "model": "stub", "elapsed_ms": 1.0}


def _plan() -> np.ndarray:
    plan = np.zeros((T, 16))
    plan[:, 0] = 1.0
    plan[:, 7:] = [0.0, -0.35, 0.0, -2.3, 0.0, 1.95, -0.7853, 0.04, 0.04]
    return plan


def test_score_retries_5xx_with_growing_waits_then_returns_the_answer(stub):
    server = stub([(503, {"error": {"rule": "not_ready"}}), (500, {}), (200, SCORE)])
    with ScoreClient(server.url, api_key="k3y", retry=FAST) as scorer:
        assert scorer.score("aW1n", _plan(), "stacking") == SCORE
    assert len(server.seen) == 3
    for seen in server.seen:
        assert (seen.method, seen.path) == ("POST", "/v1/score")
        assert seen.body == {"image": "aW1n", "plan": _plan().tolist(), "task": "stacking"}
        assert seen.headers.get("X-API-Key") == "k3y"
    gaps = np.diff([s.at for s in server.seen])
    assert gaps[0] >= 0.05 and gaps[1] >= 0.10  # base_delay, then doubled


def test_a_shedding_service_is_retried_after_its_retry_after(stub):
    """A 503 with Retry-After (the service's load shedding): the next try waits that long, not the
    policy's 50 ms; the client sends its own time budget, so the service drops what it gives up on."""
    shed = {"error": {"field": None, "rule": "overloaded", "message": "full"}}
    server = stub([(503, shed, {"Retry-After": "1"}), (200, SCORE)])
    with ScoreClient(server.url, retry=FAST, timeout=7.5) as scorer:
        assert scorer.score("aW1n", _plan(), "stacking") == SCORE
    assert len(server.seen) == 2 and server.seen[1].at - server.seen[0].at >= 1.0
    assert all(s.headers.get("X-Request-Timeout") == "7.5" for s in server.seen)


def test_calls_carry_the_request_id_of_the_work_they_belong_to(stub):
    server = stub([(200, SCORE)])
    with ScoreClient(server.url, retry=FAST) as scorer:
        with request_id("trial-4-0123456789ab"):
            scorer.score("aW1n", _plan(), "stacking")
        scorer.score("aW1n", _plan(), "stacking")
    assert server.seen[0].headers.get("X-Request-ID") == "trial-4-0123456789ab"
    assert "X-Request-ID" not in server.seen[1].headers  # outside any: the service generates one


def test_retry_after_is_capped_and_never_shortens_the_backoff():
    policy = RetryPolicy(base_delay=0.5, max_delay=4.0, max_retry_after=10.0)
    assert policy.delay(1, None) == 0.5 and policy.delay(1, 0.1) == 0.5
    assert policy.delay(1, 3.0) == 3.0 and policy.delay(2, 3600.0) == 10.0


def test_the_jitter_spreads_retries_and_never_comes_back_before_retry_after():
    """Clients refused together with Retry-After: 1 return spread over [1, 1.5) s, not all at once."""
    import random

    rng = random.Random(0)
    waits = [RetryPolicy().wait(1, 1.0, rng) for _ in range(1000)]
    assert min(waits) >= 1.0 and max(waits) < 1.5
    assert max(waits) - min(waits) > 0.45 and len({round(w, 3) for w in waits}) > 300  # spread, not a few values
    assert RetryPolicy(jitter=0.0).wait(2, None, rng) == RetryPolicy().delay(2)


def test_4xx_is_raised_at_once_with_the_services_details(stub):
    server = stub([(422, {"error": {"field": "plan", "rule": "length", "message": "T too long"}})])
    with ScoreClient(server.url, retry=FAST) as scorer, pytest.raises(RequestRejected) as err:
        scorer.score("aW1n", _plan(), "stacking")
    assert len(server.seen) == 1
    assert (err.value.status, err.value.field, err.value.rule) == (422, "plan", "length")
    assert "T too long" in str(err.value) and server.url in str(err.value)


def test_persistent_5xx_gives_up_naming_the_url(stub):
    server = stub([(502, {"detail": "bad gateway"})])
    with ScoreClient(server.url, retry=FAST) as scorer, pytest.raises(ServiceUnavailable) as err:
        scorer.score("aW1n", _plan(), "stacking")
    assert len(server.seen) == FAST.attempts
    assert server.url in str(err.value) and "HTTP 502" in str(err.value) and "bad gateway" in str(err.value)


def test_unreachable_service_is_named():
    with refusing_socket() as sock:
        url = "http://127.0.0.1:%d" % sock.getsockname()[1]
        with SimClient(url, retry=FAST) as client, pytest.raises(ServiceUnavailable) as err:
            client.start("stacking", 1)
    assert url in str(err.value) and "sim worker" in str(err.value) and "ConnectError" in str(err.value)


def test_connection_errors_are_retried_until_the_server_comes_up(stub):
    """Refused twice (nobody listens yet); the server comes up during the client's second backoff."""
    sock = refusing_socket()
    waits: list[float] = []

    def backoff(seconds: float) -> None:  # the client's wait between attempts: the server starts in the 2nd
        waits.append(seconds)
        if len(waits) == 2:
            server.append(stub([(200, SCORE)], sock=sock))

    server: list = []
    no_jitter = RetryPolicy(attempts=6, base_delay=0.1, jitter=0.0)  # the waits exactly, to compare them
    with ScoreClient("http://127.0.0.1:%d" % sock.getsockname()[1], retry=no_jitter) as scorer:
        scorer.http._sleep = backoff
        assert scorer.score("aW1n", _plan(), "replacement")["score"] == 0.8
    assert waits == [0.1, 0.2]  # exponential backoff, and no attempt after the answer
    assert len(server[0].seen) == 1


def test_a_malformed_plan_fails_before_the_network(stub):
    server = stub([(200, SCORE)])
    plan = _plan()
    plan[3, 1] = 1.0  # two categories in one step
    with ScoreClient(server.url, retry=FAST) as scorer, pytest.raises(PlanValidationError) as err:
        scorer.score("aW1n", plan, "stacking")
    assert (err.value.field, err.value.rule) == ("plan[3]", "one_hot") and server.seen == []


def test_wait_ready_polls_until_200_and_times_out_with_the_url(stub):
    server = stub([(503, {"error": {"rule": "not_ready", "message": "loading"}})] * 2 + [(200, {"status": "ready"})])
    with ScoreClient(server.url) as scorer:
        scorer.wait_ready(timeout=10)
    assert [s.path for s in server.seen] == ["/readyz"] * 3
    never = stub([(503, {"error": {"rule": "not_ready", "message": "loading the bundle"}})])
    with ScoreClient(never.url) as scorer, pytest.raises(ServiceUnavailable) as err:
        scorer.wait_ready(timeout=0.5)
    assert "after 0.5 s" in str(err.value) and len(never.seen) >= 1
    assert never.url in str(err.value) and "not ready" in str(err.value) and "loading the bundle" in str(err.value)
