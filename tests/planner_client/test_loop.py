"""The trial loop against the real embedded simulator: records, oracle, resume without double counting."""

import json

import pytest

from planner_client.embedded import EmbeddedSim
from planner_client.loop import RunConfig, read_records, run_trials, summarise
from planner_client.tamp import PlannerConfig, TampPlanner


@pytest.fixture(scope="module")
def sim_and_planner():
    sim = EmbeddedSim()
    yield sim, TampPlanner(PlannerConfig(horizon=32))
    sim.close()


def test_records_are_written_as_trials_end_and_resume_skips_them(tmp_path, sim_and_planner):
    sim, planner = sim_and_planner
    out = tmp_path / "run.jsonl"
    first = list(run_trials(RunConfig(trials=2, out=out, max_iterations=2), sim, planner))
    assert [r["trial"] for r in first] == [0, 1]
    assert len(read_records(out)) == 2
    for r in first:
        assert r["tamp_success"] in (True, False) and "oracle_success" in r
        # the oracle can only be at least as good as the first plan
        assert r["oracle_success"] or not r["tamp_success"]
    # a torn last line (killed mid-write) is dropped, and the run continues after the good records
    with out.open("a") as f:
        f.write('{"trial": 2, "se')
    more = list(run_trials(RunConfig(trials=3, out=out, max_iterations=2, resume=True), sim, planner))
    assert [r["trial"] for r in more] == [2]
    records = read_records(out)
    assert [r["trial"] for r in records] == [0, 1, 2]
    assert all(json.loads(line) for line in out.read_text().splitlines())
    assert summarise(records)["trials"] == 3


def test_existing_output_needs_resume(tmp_path, sim_and_planner):
    sim, planner = sim_and_planner
    out = tmp_path / "run.jsonl"
    out.write_text("")
    with pytest.raises(FileExistsError, match="--resume"):
        list(run_trials(RunConfig(trials=1, out=out), sim, planner))
