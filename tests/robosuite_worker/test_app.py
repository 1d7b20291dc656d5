"""The robosuite worker speaks the world API of our sim worker: the same routes, bodies and error shape."""

from __future__ import annotations

import time

import numpy as np
import pytest
from fastapi.testclient import TestClient

from firp.core.contract import make_plan
from robosuite_worker.app import create_app
from robosuite_worker.settings import RobosuiteSettings
from world_api.images import decode_png_b64


@pytest.fixture(scope="module")
def client():
    with TestClient(create_app(RobosuiteSettings(image_size=48))) as c:
        deadline = time.monotonic() + 300
        while c.get("/readyz").status_code != 200:  # the environments are made in the background
            assert time.monotonic() < deadline, c.get("/readyz").json()
            time.sleep(0.2)
        yield c


def _start(client, task="stack_three", seed=3, **extra) -> dict:
    r = client.post("/v1/episodes", json={"task": task, "seed": seed, **extra})
    assert r.status_code == 201, r.text
    return r.json()


def test_ready_names_the_world_its_tasks_and_outcome_kinds(client):
    assert client.get("/readyz").json() == {"status": "ready", "world": "robosuite_worker",
                                            "tasks": ["stack_three", "nut_assembly", "nut_assembly_round", "pick_place"],
                                            "outcome_kinds": ["success", "not_done", "unstable"], "image_size": 48,
                                            "pending": 0}


@pytest.mark.parametrize("task, objects", [("stack_three", {"cubeA", "cubeB", "cubeC"}), ("nut_assembly", {"SquareNut"}),
                                           ("pick_place", {"Milk", "Bread", "Cereal", "Can"})])
def test_an_episode_and_an_execution_over_http(client, task, objects):
    episode = _start(client, task, seed=4)
    assert set(episode["observation"]["blocks"]) == objects and episode["pose_error"] == {"mm": 3.0, "deg": 3.0}
    image = decode_png_b64(episode["image"])
    assert image.shape == (48, 48, 3) and episode["image_size"] == {"height": 48, "width": 48}
    joints = np.array(episode["robot"]["joint_positions"])
    assert joints.shape == (9,) and episode["robot"]["joint_names"][0] == "joint1"
    plan = make_plan(np.zeros(8, dtype=int), np.tile(joints, (8, 1)))
    r = client.post(f"/v1/episodes/{episode['episode_id']}/execute", json={"plan": plan.tolist(), "record_frames": True})
    assert r.status_code == 200, r.text
    out = r.json()
    assert set(out) == {"episode_id", "success", "reason", "kind", "final_blocks", "sim_seconds", "unstable", "frames"}
    assert (out["success"], out["kind"], out["unstable"]) == (False, "not_done", False)
    assert len(out["frames"]) == 8 and np.array_equal(decode_png_b64(out["frames"][0]), image)
    assert set(out["final_blocks"]) == objects
    assert client.delete(f"/v1/episodes/{episode['episode_id']}").status_code == 204


@pytest.mark.parametrize("body, field, rule", [
    ({"task": "stacking", "seed": 1}, "task", "unknown_task"),
    ({"task": "stack_three", "seed": "1"}, "seed", "int_type"),
    ({"task": "stack_three", "seed": -1}, "seed", "greater_than_equal"),
    ({"task": "stack_three", "seed": 1, "color": "red"}, "color", "extra_forbidden"),
])
def test_bad_episode_requests_name_the_field_and_the_rule(client, body, field, rule):
    r = client.post("/v1/episodes", json=body)
    assert r.status_code == 422 and r.json()["error"]["field"] == field and r.json()["error"]["rule"] == rule


def test_bad_plans_and_unknown_episodes(client):
    episode = _start(client)
    url = f"/v1/episodes/{episode['episode_id']}/execute"
    joints = np.array(episode["robot"]["joint_positions"])
    plan = make_plan(np.zeros(8, dtype=int), np.tile(joints, (8, 1)))
    narrow = client.post(url, json={"plan": plan[:, :15].tolist()})
    assert narrow.status_code == 422 and narrow.json()["error"] == {
        "field": "plan", "rule": "width", "message": narrow.json()["error"]["message"]}
    hot = plan.copy()
    hot[2, :7] = 1.0
    assert client.post(url, json={"plan": hot.tolist()}).json()["error"]["field"] == "plan[2]"
    far = plan.copy()
    far[1, 7] = 9.0
    assert client.post(url, json={"plan": far.tolist()}).json()["error"]["rule"] == "joint_limits"
    assert client.post("/v1/episodes/nope/execute", json={"plan": plan.tolist()}).json()["error"]["rule"] == \
        "unknown_episode"
    assert client.delete("/v1/episodes/nope").status_code == 404


def test_a_worker_can_serve_some_tasks_through_a_camera_only_they_have(monkeypatch):
    """FIRP_ROBOSUITE_TASKS=stack_three with FIRP_ROBOSUITE_CAMERA=workspaceview: the other tasks lack that
    camera, so a worker serving them all would never be ready; one serving stack_three alone is, and refuses
    the others by name."""
    from pydantic import ValidationError

    monkeypatch.setenv("FIRP_ROBOSUITE_TASKS", " stack_three ,")
    monkeypatch.setenv("FIRP_ROBOSUITE_CAMERA", "workspaceview")
    settings = RobosuiteSettings(image_size=32)
    assert settings.tasks == ("stack_three",) and settings.camera == "workspaceview"
    with TestClient(create_app(settings)) as c:
        deadline = time.monotonic() + 120
        while c.get("/readyz").status_code != 200:
            assert time.monotonic() < deadline, c.get("/readyz").json()
            time.sleep(0.2)
        assert c.get("/readyz").json()["tasks"] == ["stack_three"]
        episode = _start(c)
        assert decode_png_b64(episode["image"]).shape == (32, 32, 3)
        r = c.post("/v1/episodes", json={"task": "nut_assembly", "seed": 0})
        assert r.status_code == 422 and r.json()["error"]["field"] == "task"
    monkeypatch.setenv("FIRP_ROBOSUITE_TASKS", "stack_three,stacking")
    with pytest.raises(ValidationError, match="unknown task\\(s\\) 'stacking'; expected some of stack_three"):
        RobosuiteSettings()
