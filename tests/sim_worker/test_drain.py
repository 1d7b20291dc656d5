"""``python -m sim_worker serve`` under SIGTERM: the execution it had admitted is answered, readiness
says 503 at once, new work is refused, and the process exits 0 (firp.core.draining)."""

from __future__ import annotations

import os
import signal
import threading
import time

import httpx
import numpy as np
import pytest

from firp.core.contract import make_plan
from tests.processes import ServedProcess, clean_env

pytestmark = pytest.mark.slow  # make test-fast leaves this module out


def _pending(base: str) -> int:
    ready = httpx.get(f"{base}/readyz", timeout=10)
    return ready.json()["pending"] if ready.status_code == 200 else 0


def test_sigterm_finishes_the_admitted_execution_and_exits_0():
    env = clean_env("FIRP_SIM_", MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"), FIRP_SIM_DRAIN_NOTICE_S="0.5")
    answer: dict = {}
    with ServedProcess("sim_worker", ["serve", "--port", "0"], env) as worker:
        base = worker.base
        deadline = time.monotonic() + 300
        while httpx.get(f"{base}/readyz", timeout=10).status_code != 200:
            assert time.monotonic() < deadline
            time.sleep(0.2)
        episode = httpx.post(f"{base}/v1/episodes", json={"task": "stacking", "seed": 3}, timeout=60).json()
        joints = np.array(episode["robot"]["joint_positions"])
        plan = make_plan(np.zeros(240, dtype=int), np.tile(joints, (240, 1))).tolist()  # hold still: ~2 s

        def execute() -> None:
            answer["response"] = httpx.post(f"{base}/v1/episodes/{episode['episode_id']}/execute",
                                            json={"plan": plan}, timeout=120)

        client = threading.Thread(target=execute)
        client.start()
        deadline = time.monotonic() + 30
        while _pending(base) == 0:  # admitted and running on the world's thread
            assert time.monotonic() < deadline and client.is_alive(), "the execution was never seen running"
            time.sleep(0.02)
        worker.send_signal(signal.SIGTERM)
        ready = httpx.get(f"{base}/readyz", timeout=10)
        refused = httpx.post(f"{base}/v1/episodes", json={"task": "stacking", "seed": 4}, timeout=10)
        client.join(timeout=120)
        worker.wait(timeout=60)
    assert worker.returncode == 0, worker.log
    assert answer["response"].status_code == 200, answer["response"].text
    assert ready.status_code == 503 and ready.json()["error"]["rule"] == "draining"
    assert refused.status_code == 503 and refused.json()["error"]["rule"] == "not_ready"
    assert "SIGTERM: draining (1 pending" in worker.log and "drained in" in worker.log, worker.log
