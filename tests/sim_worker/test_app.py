"""The sim worker's HTTP API in process: episodes, execution, errors, the episode store's limits.

The app runs with its real worlds (built by the lifespan on the sim thread); only the clock is
injected, so episode expiry can be tested without waiting.
"""

from __future__ import annotations

import json
import time
import warnings
from datetime import datetime

import numpy as np
import pytest

with warnings.catch_warnings():  # starlette's TestClient on plain httpx: deprecated, still the documented way
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

from firp.core.contract import CATEGORY_INDEX, JOINT_UPPER, N_CATEGORIES
from planner_client.tamp import PlannerConfig, TampPlanner
from sim_worker.app import create_app
from sim_worker.backend import block_poses_json
from planner_client.collect import episode_order, simulate_episode
from world_api.images import decode_png_b64
from sim_worker.perception import PoseErrorConfig
from sim_worker.scene import RenderConfig, SceneLayout
from sim_worker.settings import SimWorkerSettings
from sim_worker.tasks import reason_kind, sample_initial_blocks
from sim_worker.world import World

T = 16
MAX_EPISODES = 5
TTL = 100.0


class FakeClock:
    def __init__(self) -> None:
        self.now = 1_800_000_000.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture(scope="module")
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture(scope="module")
def client(clock):
    settings = SimWorkerSettings(max_episodes=MAX_EPISODES, episode_ttl_seconds=TTL)
    with TestClient(create_app(settings, clock=clock)) as c:
        deadline = time.monotonic() + 60
        while c.get("/readyz").status_code != 200:
            assert time.monotonic() < deadline, c.get("/readyz").json()
            time.sleep(0.05)
        yield c


@pytest.fixture(scope="module")
def planner() -> TampPlanner:
    return TampPlanner(PlannerConfig(horizon=T))


def _start(client, task="stacking", seed=3, **extra) -> dict:
    r = client.post("/v1/episodes", json={"task": task, "seed": seed, **extra})
    assert r.status_code == 201, r.text
    return r.json()


def test_health_and_readiness(client):
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 200
    assert ready.json() == {"status": "ready", "world": "sim_worker", "tasks": ["stacking", "replacement"],
                            "outcome_kinds": ["success", "not_at_rest", "wrong_height", "tilted", "off_block_below",
                                              "not_inside", "unstable"], "image_size": 84, "pending": 0}


def test_requests_carry_a_request_id(client):
    """The planner's trial id is echoed (the worker's log line has it); a missing one is generated."""
    assert client.get("/healthz", headers={"X-Request-ID": "trial-2-00ff"}).headers["X-Request-ID"] == "trial-2-00ff"
    assert len(client.get("/healthz").headers["X-Request-ID"]) == 32
    bad = client.get("/healthz", headers={"X-Request-ID": "no spaces"})
    assert bad.status_code == 400 and bad.json()["error"]["field"] == "X-Request-ID"


@pytest.mark.parametrize("task,seed", [("stacking", 11), ("replacement", 12)])
def test_episode_image_and_observation_are_the_datasets(client, planner, task, seed):
    """frame 0 of a collected episode (same task, seed, default 84 px camera) is the episode's image,
    pixel for pixel, and the observation is what the collector's planner was given."""
    episode = _start(client, task, seed)
    image = decode_png_b64(episode["image"])
    with World(SceneLayout(), RenderConfig.for_task(task, 84, 84)) as world:
        record = simulate_episode(world, planner, task, seed, episode_order(seed), PoseErrorConfig())
    assert image.shape == (84, 84, 3) and image.dtype == np.uint8
    np.testing.assert_array_equal(image, record.frames[0])
    assert episode["image_size"] == {"height": 84, "width": 84}
    assert episode["observation"]["blocks"] == record.attrs["pose_estimates"]
    assert set(episode["observation"]["scene"]["boxes"]) == {"box_a", "box_b"}
    assert episode["robot"]["joint_positions"][-2:] == [0.04, 0.04]  # home posture, fingers open
    assert (episode["task"], episode["seed"]) == (task, seed)


def test_timestamps_follow_the_ttl(client):
    episode = _start(client)
    created = datetime.fromisoformat(episode["created_at"].replace("Z", "+00:00"))
    expires = datetime.fromisoformat(episode["expires_at"].replace("Z", "+00:00"))
    assert (expires - created).total_seconds() == pytest.approx(TTL)


def test_pose_error_override_zero_reports_the_true_poses(client):
    episode = _start(client, "stacking", 5, pose_error_mm=0, pose_error_deg=0.0)
    true = sample_initial_blocks("stacking", 5)
    got = np.array([[*b["position"], b["yaw"]] for b in episode["observation"]["blocks"].values()])
    np.testing.assert_allclose(got, true, atol=1e-12)
    assert episode["pose_error"] == {"mm": 0.0, "deg": 0.0}
    default = _start(client, "stacking", 5)
    assert default["pose_error"] == {"mm": 3.0, "deg": 3.0}
    assert default["observation"] != episode["observation"] and default["image"] == episode["image"]


def test_every_execution_starts_from_the_initial_state(client, planner):
    """Plan A, then a different plan B, then A again: A's outcome is the same both times."""
    episode = _start(client, "stacking", 4)
    url = f"/v1/episodes/{episode['episode_id']}/execute"
    plan_a = planner.plan("stacking", episode["observation"], ("red", "green", "blue")).actions
    plan_b = planner.plan("stacking", episode["observation"], ("blue", "red", "green")).actions
    first = client.post(url, json={"plan": plan_a.tolist()}).json()
    other = client.post(url, json={"plan": plan_b.tolist()}).json()
    again = client.post(url, json={"plan": plan_a.tolist()}).json()
    assert first == again
    assert other["final_blocks"] != first["final_blocks"]
    assert set(first) == {"episode_id", "success", "reason", "kind", "final_blocks", "sim_seconds", "unstable"}
    assert isinstance(first["success"], bool) and first["reason"] and first["unstable"] is False
    assert first["kind"] == reason_kind(first["success"], first["reason"])
    assert first["sim_seconds"] == pytest.approx(T / 4 + 1.5, abs=0.01)
    assert set(first["final_blocks"]) == {"red", "green", "blue"}


def test_frames_only_when_asked_and_frame_zero_is_the_episode_image(client, planner):
    episode = _start(client, "replacement", 8)
    plan = planner.plan("replacement", episode["observation"]).actions
    url = f"/v1/episodes/{episode['episode_id']}/execute"
    with_frames = client.post(url, json={"plan": plan.tolist(), "record_frames": True}).json()
    without = client.post(url, json={"plan": plan.tolist()}).json()
    assert len(with_frames["frames"]) == T and "frames" not in without
    assert with_frames["frames"][0] == episode["image"]
    assert decode_png_b64(with_frames["frames"][-1]).shape == (84, 84, 3)
    assert {k: v for k, v in with_frames.items() if k != "frames"} == without


def test_delete_then_unknown(client):
    episode = _start(client)
    assert client.delete(f"/v1/episodes/{episode['episode_id']}").status_code == 204
    r = client.delete(f"/v1/episodes/{episode['episode_id']}")
    assert r.status_code == 404 and r.json()["error"]["rule"] == "unknown_episode"


def test_episodes_expire_after_the_ttl(client, clock, planner):
    episode = _start(client)
    plan = planner.plan("stacking", episode["observation"]).actions.tolist()
    clock.now += TTL - 1
    assert client.post(f"/v1/episodes/{episode['episode_id']}/execute", json={"plan": plan}).status_code == 200
    clock.now += 2
    r = client.post(f"/v1/episodes/{episode['episode_id']}/execute", json={"plan": plan})
    assert r.status_code == 404 and r.json()["error"]["field"] == "episode_id"


def test_the_oldest_episode_is_evicted_beyond_the_maximum(client):
    ids = [_start(client, seed=s)["episode_id"] for s in range(MAX_EPISODES + 1)]
    assert client.delete(f"/v1/episodes/{ids[0]}").status_code == 404  # evicted
    assert all(client.delete(f"/v1/episodes/{i}").status_code == 204 for i in ids[1:])


def _plan_rows(modify=None) -> list:
    plan = np.zeros((T, 16))
    plan[:, CATEGORY_INDEX["move"]] = 1.0
    plan[:, N_CATEGORIES:] = [0.0, -0.35, 0.0, -2.3, 0.0, 1.95, -0.7853, 0.04, 0.04]
    rows = plan.tolist()
    if modify:
        modify(rows)
    return rows


def _set(step, col, value):
    def modify(rows):
        rows[step][col] = value
    return modify


BAD_EPISODES = [
    ({"task": "juggling", "seed": 1}, "task", "unknown_task"),
    ({"task": "stacking", "seed": -1}, "seed", "greater_than_equal"),
    ({"task": "stacking", "seed": 1.5}, "seed", "int_type"),
    ({"task": "stacking", "seed": "3"}, "seed", "int_type"),
    ({"task": "stacking", "seed": True}, "seed", "int_type"),
    ({"task": "stacking", "seed": 2**64}, "seed", "less_than_equal"),
    ({"task": "stacking"}, "seed", "missing"),
    ({"seed": 1}, "task", "missing"),
    ({"task": "stacking", "seed": 1, "pose_error_mm": -0.5}, "pose_error_mm", "greater_than_equal"),
    ({"task": "stacking", "seed": 1, "sed": 2}, "sed", "extra_forbidden"),
]


@pytest.mark.parametrize("body,field,rule", BAD_EPISODES, ids=[f"{f}-{r}" for _, f, r in BAD_EPISODES])
def test_bad_episode_requests(client, body, field, rule):
    r = client.post("/v1/episodes", json=body)
    assert r.status_code == 422
    error = r.json()["error"]
    assert (error["field"], error["rule"]) == (field, rule) and error["message"]
    assert set(r.json()) == {"error"}


BAD_PLANS = [
    ({"plan": _plan_rows()[:3]}, "plan", "length"),
    ({"plan": [row[:15] for row in _plan_rows()]}, "plan", "width"),
    ({"plan": _plan_rows(_set(2, CATEGORY_INDEX["grasp"], 1.0))}, "plan[2]", "one_hot"),
    ({"plan": _plan_rows(_set(5, N_CATEGORIES + 1, float(JOINT_UPPER[1]) + 1.0))}, "plan[5][8]", "joint_limits"),
    ({"plan": _plan_rows(_set(0, 9, "0.5"))}, "plan", "numeric"),
    ({"plan": _plan_rows()[:-1] + [[0.0] * 10]}, "plan", "numeric"),  # ragged
    ({"plan": "not a plan"}, "plan", "list_type"),
    ({"plan": [1, 2, 3]}, "plan[0]", "list_type"),
    ({}, "plan", "missing"),
    ({"plan": _plan_rows(), "record_frames": "yes"}, "record_frames", "bool_type"),
]


@pytest.mark.parametrize("body,field,rule", BAD_PLANS, ids=[f"{f}-{r}" for _, f, r in BAD_PLANS])
def test_bad_execute_requests(client, body, field, rule):
    episode = _start(client)
    r = client.post(f"/v1/episodes/{episode['episode_id']}/execute", json=body)
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert (error["field"], error["rule"]) == (field, rule) and error["message"]


def test_malformed_json_unknown_episode_and_route_share_the_error_shape(client):
    r = client.post("/v1/episodes", content=b'{"task": "stacking",', headers={"content-type": "application/json"})
    assert r.status_code == 422 and r.json()["error"]["field"] == "body" and r.json()["error"]["rule"] == "json_invalid"
    r = client.post("/v1/episodes/0123/execute", json={"plan": _plan_rows()})
    assert r.status_code == 404 and r.json()["error"]["field"] == "episode_id"
    assert r.json()["error"]["rule"] == "unknown_episode" and "same task and seed" in r.json()["error"]["message"]
    r = client.get("/v1/nothing")
    assert r.status_code == 404 and r.json() == {"error": {"field": None, "rule": "not_found", "message": "Not Found"}}
    r = client.get("/v1/episodes")
    assert r.status_code == 405 and r.json()["error"]["rule"] == "method_not_allowed"


def test_lost_physics_is_reported_as_null_coordinates_not_a_server_error():
    """The executor flags a diverged simulation as ``unstable`` (a failed result); the coordinates it
    then reads back may be NaN, which JSON cannot carry -- they must come out as null. (No plan within
    the joint limits was found that makes this scene diverge, so this checks the conversion.)"""
    poses = sample_initial_blocks("stacking", 0)
    poses[1, 2] = np.nan
    poses[2, 3] = np.inf
    out = block_poses_json(poses)
    assert out["green"]["position"][2] is None and out["blue"]["yaw"] is None
    assert out["red"]["position"] == poses[0, :3].tolist()
    json.dumps(out, allow_nan=False)
