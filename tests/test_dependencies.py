"""The architecture's dependency rules, checked by importing each part in a clean interpreter."""

import json
import subprocess
import sys

import pytest

PROBE = """
import importlib, json, sys
for name in {modules!r}:
    importlib.import_module(name)
print(json.dumps(sorted(m for m in ("torch", "mujoco") if m in sys.modules)))
"""


def _heavy_modules_after_importing(modules: list[str]) -> list[str]:
    out = subprocess.run([sys.executable, "-c", PROBE.format(modules=modules)], capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_contract_and_episodes_import_neither_torch_nor_mujoco():
    assert _heavy_modules_after_importing(["firp.contract", "firp.episodes"]) == []


@pytest.mark.parametrize("modules", [
    ["sim_worker.world", "sim_worker.executor", "sim_worker.collect", "sim_worker.__main__"],
    ["sim_worker.app", "sim_worker.settings", "sim_worker.schemas"],
    ["planner_client.tamp", "planner_client.ik"],
    ["planner_client.clients", "planner_client.launcher", "planner_client.embedded", "planner_client.__main__"],
])
def test_sim_worker_and_planner_never_import_torch(modules):
    assert "torch" not in _heavy_modules_after_importing(modules)


def test_service_never_imports_mujoco():
    modules = ["service.app", "service.v2", "service.__main__"]
    assert "mujoco" not in _heavy_modules_after_importing(modules)
