"""The rounds of learning from deployment, end to end at toy size: a real scoring service kept up across
the rounds, ``firp run --record --explore`` against it with launched sim workers, ``firp refresh`` on the
collected set plus the recordings, the swap when promoted, the final run on new seeds, the report; and a
second call that finds every step done and runs nothing again."""

from __future__ import annotations

import json

import pytest

from experiments.bundle_generations import main as generations_main
from experiments.exploration_value import main as exploration_main
from experiments.learning_rounds import candidate_auc, candidate_auc_interval, main, success_interval
from firp.tune import main as tune_main
from tests.firp.learnable import T, learnable_dataset

pytestmark = pytest.mark.slow  # make test-fast leaves this module out


def test_candidate_auc_pools_every_executed_candidate():
    records = [{"candidate_scores": {"a": 0.9, "b": 0.2, "c": 0.5}, "candidate_outcomes": {"a": True, "b": False}},
               {"candidate_scores": {"a": 0.4, "b": 0.6}, "candidate_outcomes": {"a": False, "b": True}}]
    assert candidate_auc(records) == 1.0  # c was never executed: no label, left out
    assert candidate_auc([{"candidate_scores": {"a": 0.9}, "candidate_outcomes": {"a": True}}]) is None


def test_intervals_cover_the_point_and_narrow_with_more_scenes():
    records = [{"candidate_scores": {"a": 0.9, "b": 0.2, "c": 0.6}, "candidate_outcomes": {"a": True, "b": False,
                                                                                          "c": False}},
               {"candidate_scores": {"a": 0.4, "b": 0.6}, "candidate_outcomes": {"a": False, "b": True}},
               {"candidate_scores": {"a": 0.7, "b": 0.8}, "candidate_outcomes": {"a": True, "b": False}}]
    low, high = candidate_auc_interval(records * 4, resamples=300)
    assert low <= candidate_auc(records * 4) <= high and high - low > 0.05
    wide = candidate_auc_interval(records * 4, resamples=300)
    narrow = candidate_auc_interval(records * 40, resamples=300)
    assert narrow[1] - narrow[0] < wide[1] - wide[0]
    assert candidate_auc_interval([{"candidate_scores": {"a": 0.9}, "candidate_outcomes": {"a": True}}]) is None
    low, high = success_interval(79, 100)
    assert 0.69 < low < 0.71 and 0.85 < high < 0.87  # Wilson: [0.700, 0.858]
    low, high = success_interval(0, 10)
    assert abs(low) < 1e-9 and 0.2 < high < 0.3  # none of 10: up to 28%


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
    # what exploration's labels were worth: refreshes on the round's recording under each policy, judged on
    # every candidate of the final run
    stem = tmp_path / "report" / "exploration"
    assert exploration_main(["--bundle", str(bundle), "--data", str(collected), "--recording",
                             str(tmp_path / "rounds" / "round-0"), "--evaluation", str(tmp_path / "rounds" / "final"),
                             "--k", "1", "--epochs", "1", "--threads", "1", "--resamples", "50",
                             "--out", str(tmp_path / "exploration"), "--report", str(stem), "--no-progress"]) == 0
    table = json.loads(stem.with_suffix(".json").read_text())
    policies = [row["policy"] for row in table["rows"]]
    assert policies == ["bundle in use (no refresh)", "deployed", "least-sure-1", "random-1", "all"]
    recorded = {row["policy"]: row["recorded"] for row in table["rows"]}
    assert recorded["deployed"] == 3 and recorded["least-sure-1"] == recorded["random-1"] == 6  # one more per scene
    assert recorded["all"] == first["candidates_executed"]
    assert table["evaluation_candidates"] == final["candidates_executed"]
    assert all(0.0 <= row["candidate_auc"] <= 1.0 for row in table["rows"])
    assert "versus_deployed" in table["rows"][2] and "versus_deployed" not in table["rows"][1]
    assert stem.with_suffix(".png").stat().st_size > 0
    # every bundle of the rounds on the final run's candidates, paired against the shipped one
    stem = tmp_path / "report" / "generations"
    assert generations_main(["--rounds", str(tmp_path / "rounds"), "--first", str(bundle), "--evaluation",
                             str(tmp_path / "rounds" / "final"), "--threads", "1", "--resamples", "50",
                             "--report", str(stem)]) == 0
    shipped, *refreshed = json.loads(stem.with_suffix(".json").read_text())["rows"]
    assert shipped["version"] == first["model_version"] and "versus_shipped" not in shipped
    # a refresh that ran wrote its bundle, promoted or kept; one refused for its data (toy sizes) wrote none
    assert len(refreshed) == int((tmp_path / "rounds" / "round-0" / "bundle" / "manifest.json").exists())
    for row in refreshed:
        assert row["bundle"].startswith("refresh after round 0 (") and "versus_shipped" in row
        assert row["bundle"].endswith("(promoted)") == refresh["promoted"]
