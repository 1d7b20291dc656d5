"""The main job's loop in the robosuite world: the planner's choices as candidates, the worker launched."""

from __future__ import annotations

import json

from planner_client.__main__ import main
from planner_client.loop import read_records
from planner_client.robosuite_tamp import RobosuiteTampPlanner


def test_a_run_without_scoring_launches_the_worker_and_walks_the_choices(tmp_path, capsys):
    out = tmp_path / "run.jsonl"
    assert main(["run", "--world", "robosuite", "--task", "stack_three", "--trials", "2", "--no-score",
                 "--max-iterations", "3", "--out", str(out)]) == 0
    records = read_records(out)
    assert [r["seed"] for r in records] == [100_000, 100_001]
    assert all(r["run"]["horizon"] == 80 and r["run"]["task"] == "stack_three" for r in records)
    labels = [c.label() for c in RobosuiteTampPlanner().choices("stack_three", {"blocks": dict.fromkeys(
        ("cubeA", "cubeB", "cubeC"))})[:3]]
    for record in records:
        assert 1 <= record["executions"] <= 3
        if record["tamp_success"]:  # the default choice succeeded: the oracle takes it, nothing more is run
            assert (record["oracle_order"], record["executions"]) == (labels[0], 1)
        elif record["oracle_success"]:
            assert record["oracle_order"] in labels[1:]
        assert record["tamp_reason"].startswith("StackThree: ")
    summary = json.loads(out.with_suffix(".summary.json").read_text())
    assert summary["all_trials"]["tamp"]["trials"] == 2
    assert "oracle (first of 3 planner choices that succeeds in simulation)" in capsys.readouterr().out
