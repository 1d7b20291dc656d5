"""The main job's first committed trials (``docs/results/main_job/<task>-50.jsonl``), run again.

``python -m planner_client run`` exactly as ``make run`` starts it -- both services launched on
loopback, the scoring service on the shipped bundle of the task (EfficientNet-Lite0 at 84 px, eight
plan steps per transition, the plan's grasp-frame description, attention temperature 0.05) -- for the
first trials of each committed run. Each record must equal the committed one: the model version and its
validation evidence, every candidate's score, which order was accepted after how many plans (or, for
the uninformative replacement bundle, that TAMP's first plan was executed), every decision rule's pick
and outcome, and the outcome of TAMP alone, of TAMP + FIRP and of the oracle line.
"""

from __future__ import annotations

import pytest

from planner_client.__main__ import main
from planner_client.loop import read_records
from sim_worker.tasks import reason_kind

from .conftest import read_jsonl

TRIALS = 3
TIMING = ("start_s", "plan_s", "score_s", "execute_s", "seconds")
IDENTIFIERS = ("request_id",)  # new per run: it finds a trial's calls in the services' logs
REASONS = ("tamp", "firp")
SCORES = ("scores", "candidate_scores")  # floats from another machine's torch: compared to 2e-6 below  # <line>_success + <line>_reason: compared as kinds


def _comparable(record: dict) -> dict:
    out = {k: v for k, v in record.items() if k not in TIMING + IDENTIFIERS + SCORES}
    for line in REASONS:
        out[f"{line}_reason"] = reason_kind(record[f"{line}_success"], record[f"{line}_reason"])
    return out


@pytest.mark.parametrize("task", ["stacking", "replacement"])
def test_the_first_trials_of_the_committed_main_job_come_out_the_same(tmp_path, task):
    committed = read_jsonl(f"main_job/{task}-50.jsonl", first=TRIALS)
    out = tmp_path / "runs" / f"{task}.jsonl"
    assert main(["run", "--trials", str(TRIALS), "--task", task, "--out", str(out)]) == 0
    records = read_records(out)
    assert [r["trial"] for r in records] == list(range(TRIALS))
    for got, want in zip(records, committed):
        assert got["scores"] == pytest.approx(want["scores"], abs=2e-6), got["trial"]
        assert got["candidate_scores"].keys() == want["candidate_scores"].keys()
        assert list(got["candidate_scores"].values()) == pytest.approx(list(want["candidate_scores"].values()), abs=2e-6)
        assert _comparable(got) == _comparable(want)
