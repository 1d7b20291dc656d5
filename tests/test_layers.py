"""The layers of the data flow, checked on every module of every package, each in a fresh interpreter.

    firp.core        the shared, torch-free core: plan contract, episode format, error shape, CLI
                     argument types, bundle format -- imports no torch, no MuJoCo, no other part
    world_api        the HTTP API every world serves: the core only (no torch, no MuJoCo, no world)
    sim_worker       our MuJoCo world: the core and the world API (no torch, no planner, no method, no service)
    planner_client   the planner, the loop, dataset collection: the core and a world (no torch)
    firp (method)    model, training, bundles, serving path: the core (no MuJoCo, no world, no planner)
    service          the scoring service: the method and the core (no MuJoCo, no world, no planner)
    firp_cli         the ``firp`` command: imports a part only when its subcommand runs (nothing at import)
    experiments      research analyses: may use every part, and each must import on its own

A module passes if importing it *alone* pulls in none of its layer's forbidden modules: the walk
uses :func:`pkgutil.walk_packages`, so a new module is checked without being listed here.
"""

from __future__ import annotations

import json
import pkgutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # make test-fast leaves this module out

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("firp", "world_api", "sim_worker", "planner_client", "service", "firp_cli", "experiments")
WORLD, PLANNER, SERVICE, METHOD = "sim_worker", "planner_client", "service", "firp"

#: layer -> module prefixes it must never import ("firp" alone means the method: firp.core is allowed)
FORBIDDEN = {
    "firp.core": ("torch", "mujoco", WORLD, PLANNER, SERVICE, METHOD, "world_api"),
    "world_api": ("torch", "mujoco", WORLD, PLANNER, SERVICE, METHOD),
    WORLD: ("torch", PLANNER, SERVICE, METHOD),
    PLANNER: ("torch", SERVICE, METHOD),
    METHOD: ("mujoco", WORLD, PLANNER, SERVICE),
    SERVICE: ("mujoco", WORLD, PLANNER),
    "firp_cli": ("torch", "mujoco", WORLD, PLANNER, SERVICE, METHOD),
    "experiments": (),
}

PROBE = "import importlib, json, sys; importlib.import_module(sys.argv[1]); print(json.dumps(sorted(sys.modules)))"


def layer_of(module: str) -> str:
    return "firp.core" if module == "firp.core" or module.startswith("firp.core.") else module.split(".")[0]


def violates(loaded: str, prefix: str) -> bool:
    """``loaded`` is (inside) ``prefix``; the method's prefix "firp" leaves out the core and the package's face."""
    if prefix == METHOD:
        return loaded.startswith("firp.") and layer_of(loaded) != "firp.core"
    return loaded == prefix or loaded.startswith(prefix + ".")


def every_module() -> list[str]:
    names = []
    for package in PACKAGES:
        names.append(package)
        names += [m.name for m in pkgutil.walk_packages([str(ROOT / package)], prefix=f"{package}.")]
    return sorted(names)


@pytest.fixture(scope="module")
def imported() -> dict[str, list[str]]:
    """module -> every module loaded by importing it alone (two interpreters at a time)."""
    def probe(module: str) -> tuple[str, list[str]]:
        out = subprocess.run([sys.executable, "-c", PROBE, module], capture_output=True, text=True, cwd=ROOT)
        assert out.returncode == 0, f"importing {module} alone fails:\n{out.stderr[-2000:]}"
        return module, json.loads(out.stdout.strip().splitlines()[-1])

    with ThreadPoolExecutor(2) as pool:
        return dict(pool.map(probe, every_module()))


def test_the_walk_finds_every_part():
    modules = every_module()
    for expected in ("firp.core.contract", "firp.core.episodes", "firp.core.http_errors", "firp.core.bundle_format",
                     "sim_worker.executor", "planner_client.collect", "planner_client.loop", "service.app",
                     "firp_cli", "experiments.replan_threshold", "experiments.tcr_ablation"):
        assert expected in modules
    assert len(modules) > 60


def test_no_module_imports_what_its_layer_forbids(imported):
    broken = []
    for module, loaded in imported.items():
        for prefix in FORBIDDEN[layer_of(module)]:
            hits = sorted(m for m in loaded if violates(m, prefix))
            if hits:
                broken.append(f"{module} ({layer_of(module)}) imports {prefix}: {', '.join(hits[:3])}")
    assert not broken, "\n".join(broken)
