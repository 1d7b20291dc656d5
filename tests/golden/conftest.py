"""Golden replays: what the committed results say the product did, done again and compared.

The files under ``docs/results`` are the project's published numbers. These tests re-run a
CI-sized sample of what produced them -- simulated executions, the main job's first trials, the
shipped bundles' scores -- and compare outcome by outcome, so a change to the physics, the planner,
the scorer or the loop that would change a published number turns the suite red. Outcomes are
compared by *kind* (:data:`sim_worker.tasks.OUTCOME_KINDS`), not by their text, which names blocks
and rounded numbers.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "docs" / "results"


def read_json(relative: str) -> dict:
    return json.loads((RESULTS / relative).read_text())


def read_jsonl(relative: str, first: int | None = None) -> list[dict]:
    lines = (RESULTS / relative).read_text().splitlines()
    return [json.loads(line) for line in lines[:first]]


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Every test under tests/golden is a golden replay (``-m "not golden"`` leaves them out)."""
    here = Path(__file__).parent
    for item in items:
        if here in item.path.parents:
            item.add_marker(pytest.mark.golden)
