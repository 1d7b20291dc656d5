"""Choosing the world on the planner's command line: the robosuite world's rules, before anything starts.

(The robosuite world's own runs and collections are tested in its environment: tests/robosuite_worker.)"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _cli(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "planner_client", *args], capture_output=True, text=True, cwd=ROOT,
                          timeout=120, env={**os.environ, **(env or {})})


@pytest.mark.parametrize(("args", "message"), [
    (["collect", "--world", "robosuite", "--task", "stacking", "--episodes", "1", "--out", "x.h5"],
     "--task: 'stacking' is not a task of the robosuite world; one of stack_three, nut_assembly, nut_assembly_round, pick_place"),
    (["collect", "--task", "stack_three", "--episodes", "1", "--out", "x.h5"],
     "--task: 'stack_three' is not a task of the mujoco world; one of stacking, replacement"),
    (["run", "--world", "robosuite", "--horizon", "60", "--no-score"],
     "--horizon: the robosuite world's tasks have a fixed T"),
])
def test_a_wrong_world_task_or_horizon_is_refused_naming_the_flag(args, message):
    out = _cli(*args)
    assert out.returncode == 2 and message in out.stderr, out.stderr


def test_without_a_robosuite_environment_the_error_says_how_to_make_one(tmp_path):
    missing = tmp_path / "no-such-python"
    for args in (["run", "--world", "robosuite", "--no-score", "--trials", "1"],
                 ["collect", "--world", "robosuite", "--task", "stack_three", "--episodes", "1", "--out",
                  str(tmp_path / "x.h5")]):
        out = _cli(*args, env={"FIRP_ROBOSUITE_PYTHON": str(missing)})
        assert out.returncode == 2, out.stderr
        assert f"no robosuite environment at FIRP_ROBOSUITE_PYTHON={missing}" in out.stderr
        assert "make robosuite-install" in out.stderr
    assert not (tmp_path / "x.h5").exists()
