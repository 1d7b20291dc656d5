"""``python -m sim_worker serve`` under SIGTERM: the execution it had admitted is answered, readiness
says 503 at once, new work is refused, and the process exits 0 (firp.core.draining)."""

from __future__ import annotations

import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np

from firp.core.contract import make_plan

ROOT = Path(__file__).resolve().parents[2]
LISTENING = re.compile(r"Uvicorn running on http://127\.0\.0\.1:(\d+)")


def test_sigterm_finishes_the_admitted_execution_and_exits_0():
    env = {k: v for k, v in os.environ.items() if not k.startswith("FIRP_SIM_")}
    env.update(PYTHONPATH=str(ROOT), MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"), FIRP_SIM_DRAIN_NOTICE_S="0.5")
    proc = subprocess.Popen([sys.executable, "-m", "sim_worker", "serve", "--port", "0"], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    seen: queue.Queue[str | None] = queue.Queue()

    def pump() -> None:
        for line in proc.stderr:
            lines.append(line)
            seen.put(line)
        seen.put(None)

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    answer: dict = {}
    try:
        while True:
            line = seen.get(timeout=300)
            assert line is not None, "the worker exited before listening:\n" + "".join(lines)
            if match := LISTENING.search(line):
                break
        base = f"http://127.0.0.1:{match.group(1)}"
        deadline = time.monotonic() + 300
        while httpx.get(f"{base}/readyz", timeout=10).status_code != 200:
            assert time.monotonic() < deadline
            time.sleep(0.2)
        episode = httpx.post(f"{base}/v1/episodes", json={"task": "stacking", "seed": 3}, timeout=60).json()
        joints = np.array(episode["robot"]["joint_positions"])
        plan = make_plan(np.zeros(120, dtype=int), np.tile(joints, (120, 1))).tolist()  # hold still: ~1 s

        def execute() -> None:
            answer["response"] = httpx.post(f"{base}/v1/episodes/{episode['episode_id']}/execute",
                                            json={"plan": plan}, timeout=120)

        worker = threading.Thread(target=execute)
        worker.start()
        time.sleep(0.3)  # admitted and running on the world's thread
        proc.send_signal(signal.SIGTERM)
        ready = httpx.get(f"{base}/readyz", timeout=10)
        refused = httpx.post(f"{base}/v1/episodes", json={"task": "stacking", "seed": 4}, timeout=10)
        worker.join(timeout=120)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        reader.join(timeout=30)
    err = "".join(lines)
    assert proc.returncode == 0, err
    assert answer["response"].status_code == 200, answer["response"].text
    assert ready.status_code == 503 and ready.json()["error"]["rule"] == "draining"
    assert refused.status_code == 503 and refused.json()["error"]["rule"] == "not_ready"
    assert "SIGTERM: draining (1 pending" in err and "drained in" in err
