"""The same task, seed and plan give the same label and the same frames in two separate processes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

CHILD = textwrap.dedent("""
    import hashlib, json
    import numpy as np
    from firp.core.contract import make_plan
    from robosuite_worker.world import RobosuiteWorld
    world = RobosuiteWorld(image_size=32)
    start = world.begin("stack_three", 11, 3.0, 3.0)
    targets = np.tile(start.joint_positions, (16, 1))
    targets[8:, 0] += 0.4  # swing the arm: contacts and physics, not a still scene
    targets[8:, 7:] = 0.0
    outcome = world.execute(start, make_plan(np.zeros(16, dtype=int), targets), record_frames=True)
    print(json.dumps({"success": outcome.success, "kind": outcome.kind, "final": outcome.final_blocks,
                      "frames": hashlib.sha256(outcome.frames.tobytes()).hexdigest(),
                      "image": hashlib.sha256(start.image.tobytes()).hexdigest()}))
""")


def _run() -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    out = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_two_processes_give_the_same_label_and_frames():
    assert _run() == _run()
