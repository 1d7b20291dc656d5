"""``python -m robosuite_worker serve`` as an operator starts it, and the planner's own client against it."""

from __future__ import annotations

import os
import queue
import re
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np

from firp.core.contract import make_plan
from planner_client.clients import SimClient

ROOT = Path(__file__).resolve().parents[2]
LISTENING = re.compile(r"Uvicorn running on http://127\.0\.0\.1:(\d+)")


def test_the_worker_serves_the_planners_sim_client_unchanged():
    env = {k: v for k, v in os.environ.items() if not k.startswith("FIRP_ROBOSUITE_")}
    env.update(PYTHONPATH=str(ROOT), FIRP_ROBOSUITE_IMAGE_SIZE="48")
    proc = subprocess.Popen([sys.executable, "-m", "robosuite_worker", "serve", "--port", "0"], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lines: queue.Queue[str | None] = queue.Queue()

    def pump() -> None:
        for line in proc.stderr:
            lines.put(line)
        lines.put(None)

    threading.Thread(target=pump, daemon=True).start()
    try:
        while True:
            line = lines.get(timeout=300)
            assert line is not None, "the worker exited before listening"
            if match := LISTENING.search(line):
                break
        with SimClient(f"http://127.0.0.1:{match.group(1)}") as sim:
            sim.wait_ready(timeout=300)
            episode = sim.start("nut_assembly", 2)
            assert episode.image_size == (48, 48) and "SquareNut" in episode.observation["blocks"]
            joints = np.array(episode.robot["joint_positions"])
            outcome = sim.execute(episode, make_plan(np.zeros(8, dtype=int), np.tile(joints, (8, 1))))
            assert (outcome.success, outcome.kind, outcome.unstable) == (False, "not_done", False)
            again = sim.execute(episode, make_plan(np.zeros(8, dtype=int), np.tile(joints, (8, 1))))
            assert again.final_blocks == outcome.final_blocks
    finally:
        proc.terminate()
        proc.wait(timeout=60)
    assert proc.returncode in (0, -15)
