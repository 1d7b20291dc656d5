"""The rounds of learning from deployment, end to end at toy size: a real scoring service kept up across
the rounds, ``firp run --record --explore`` against it with launched sim workers, ``firp refresh`` on the
collected set plus the recordings, the swap when promoted, the final run on new seeds, the report; and a
second call that finds every step done and runs nothing again."""

from __future__ import annotations

import json

from experiments.learning_rounds import candidate_auc, main
from firp.tune import main as tune_main
from tests.firp.learnable import T, learnable_dataset


def test_candidate_auc_pools_every_executed_candidate():
    records = [{"candidate_scores": {"a": 0.9, "b": 0.2, "c": 0.5}, "candidate_outcomes": {"a": True, "b": False}},
               {"candidate_scores": {"a": 0.4, "b": 0.6}, "candidate_outcomes": {"a": False, "b": True}}]
    assert candidate_auc(records) == 1.0  # c was never executed: no label, left out
    assert candidate_auc([{"candidate_scores": {"a": 0.9}, "candidate_outcomes": {"a": True}}]) is None


def test_rounds_record_refresh_swap_and_resume(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    collected = learnable_dataset(tmp_path / "collected", "image", n=32)
    bundle = tmp_path / "bundle"
    assert tune_main(["--data", str(collected), "--trials", "1", "--epochs", "1", "--threads", "1", "--image-size",
                      "32", "--storage", f"sqlite:///{tmp_path / 's.db'}", "--no-progress", "--space", "paper",
                      "--export", str(bundle), "--reliability", str(tmp_path / "r.png")]) == 0
    argv = ["--bundle", str(bundle), "--data", str(collected), "--rounds", "1", "--trials", "3", "--seed", "300000",
            "--explore", "6", "--parallel", "1", "--epochs", "2", "--threads", "1", "--horizon", str(T),
            "--out", str(tmp_path / "rounds"), "--report", str(tmp_path / "report" / "rounds")]
    assert main(argv) == 0
    result = json.loads((tmp_path / "report" / "rounds.json").read_text())
    first, final = result["rows"]
    assert (first["run"], final["run"]) == ("round 0", "after the rounds")
    assert first["seeds"] == [300000, 300002] and final["seeds"] == [300003, 300005]  # new seeds each run
    assert first["candidates_executed"] >= 3 and 0.0 <= first["tamp_success"] <= 1.0
    (refresh,) = result["refreshes"]
    served = final["model_version"]
    assert (served != first["model_version"]) == refresh["promoted"]  # the final run scored with the swapped-in one
    assert (tmp_path / "rounds" / "round-0" / "executions.h5").exists()
    assert (tmp_path / "report" / "rounds.png").stat().st_size > 0
    assert "| round 0 |" in (tmp_path / "report" / "rounds.md").read_text()
    # everything done: a second call only reads the files back
    before = (tmp_path / "rounds" / "round-0" / "trials.jsonl").stat().st_mtime_ns
    assert main(argv) == 0
    assert (tmp_path / "rounds" / "round-0" / "trials.jsonl").stat().st_mtime_ns == before
    assert json.loads((tmp_path / "report" / "rounds.json").read_text())["rows"] == result["rows"]
