"""The committed analyses regenerate unchanged from their committed records.

The replanning-threshold replays (``experiments.replan_threshold --analyse-only``) and the ceiling
studies (``experiments.outcome_sensitivity --records``) are pure functions of their records: run
again on the committed records, each must write exactly the committed JSON (its ``command`` line
aside, which names the script as it was called then). A change to the loop's accept rule, to the
threshold choice, to the metrics or to the analyses' bookkeeping turns these red.
"""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys

import pytest

from .conftest import RESULTS, ROOT

VOLATILE = ("command", "machine", "records_made_by")
REPLAYS = {"replan_threshold": "replan_threshold_stacking", "replan_threshold_geometry": "replan_threshold_stacking_geometry",
           "replan_threshold_previous_bundle": "replan_threshold_stacking_previous_bundle"}
CEILINGS = sorted(p.name for p in RESULTS.glob("outcome_sensitivity_*.json"))


def _run(module: str, *args: str) -> None:
    out = subprocess.run([sys.executable, "-m", module, *args], cwd=ROOT, capture_output=True, text=True,
                         timeout=300, env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    assert out.returncode == 0, out.stderr[-2000:]


def _same(committed: dict, regenerated: dict) -> None:
    for key in VOLATILE:
        committed.pop(key, None)
        regenerated.pop(key, None)
    differing = sorted(k for k in set(committed) | set(regenerated) if committed.get(k) != regenerated.get(k))
    assert not differing, differing


@pytest.mark.parametrize("records, result", sorted(REPLAYS.items()))
def test_the_threshold_replays_regenerate_unchanged(tmp_path, records, result):
    out = tmp_path / f"{result}.json"
    _run("experiments.replan_threshold", "--task", "stacking", "--analyse-only", "--records-dir",
         f"docs/results/{records}", "--out", str(out))
    _same(json.loads((RESULTS / f"{result}.json").read_text()), json.loads(out.read_text()))


@pytest.mark.parametrize("result", CEILINGS)
def test_the_ceiling_studies_regenerate_unchanged_from_their_records(tmp_path, result):
    committed = json.loads((RESULTS / result).read_text())
    words = shlex.split(committed["command"])
    flags = words[next(i for i, w in enumerate(words) if w.endswith("outcome_sensitivity")
                       or w.endswith("outcome_sensitivity.py")) + 1:]
    records = result.removeprefix("outcome_sensitivity_").removesuffix(".json").replace("_geometry_bundle", "")
    out = tmp_path / result
    _run("experiments.outcome_sensitivity", *flags, "--records", f"docs/results/outcome_sensitivity/{records}.jsonl",
         "--out", str(out))
    _same(committed, json.loads(out.read_text()))


def test_every_ceiling_study_is_checked():
    assert len(CEILINGS) == 7
