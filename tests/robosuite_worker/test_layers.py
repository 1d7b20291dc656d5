"""The robosuite worker imports the shared core and the world API only: no torch, no planner, no method,
no service, no other world -- each module imported alone, in a fresh interpreter of its own environment."""

from __future__ import annotations

import json
import pkgutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
FORBIDDEN = ("torch", "planner_client", "service", "sim_worker")
PROBE = "import importlib, json, sys; importlib.import_module(sys.argv[1]); print(json.dumps(sorted(sys.modules)))"


def test_every_module_imports_alone_and_nothing_forbidden():
    modules = ["robosuite_worker", *(m.name for m in pkgutil.walk_packages([str(ROOT / "robosuite_worker")],
                                                                            prefix="robosuite_worker."))]
    assert {"robosuite_worker.world", "robosuite_worker.envs.stack_three", "robosuite_worker.app"} <= set(modules)
    broken = []
    for module in modules:
        out = subprocess.run([sys.executable, "-c", PROBE, module], capture_output=True, text=True, cwd=ROOT,
                             timeout=120)
        assert out.returncode == 0, f"importing {module} alone fails:\n{out.stderr[-2000:]}"
        loaded = json.loads(out.stdout.strip().splitlines()[-1])
        method = [m for m in loaded if m.startswith("firp.") and not m.startswith("firp.core")]
        hits = [m for m in loaded if m.split(".")[0] in FORBIDDEN] + method
        if hits:
            broken.append(f"{module} imports {', '.join(sorted(hits)[:3])}")
    assert not broken, "\n".join(broken)
