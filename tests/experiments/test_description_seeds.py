"""The seeds-and-thresholds analysis of a small MLP on the plan's description, and the protocol records' thresholds."""

from __future__ import annotations

import json

import numpy as np
import pytest

from experiments.description_seeds import main, protocol_thresholds, recipes


def test_recipes_choose_by_validation_and_average_scores():
    y_valid = np.array([True, True, False, False])
    y_test = np.array([True, False, True, False])
    # seed 0 separates validation and test at 0.5; seed 1 only with a threshold of 0.8; seed 2 never
    p_valid = np.array([[0.9, 0.8, 0.1, 0.2], [0.95, 0.9, 0.7, 0.6], [0.1, 0.2, 0.9, 0.8]])
    p_test = np.array([[0.7, 0.3, 0.6, 0.4], [0.99, 0.6, 0.85, 0.65], [0.2, 0.9, 0.3, 0.8]])
    out = recipes(y_valid, p_valid, y_test, p_test)
    assert out["one seed, threshold 0.5"] == [1.0, 0.5, 0.0]
    assert out["one seed, validation threshold"][1] == 1.0  # the threshold chosen on validation fits it
    assert out["best of 3 seeds, threshold 0.5"] == [1.0]  # seed 0 is best on validation
    mean = p_test.mean(axis=0) >= 0.5
    assert out["mean of 3 seeds, threshold 0.5"] == [float(np.mean([mean[0], not mean[1], mean[2], not mean[3]]))]
    assert out["mean of all 3 seeds, threshold 0.5"] == out["mean of 3 seeds, threshold 0.5"]


def test_protocol_thresholds_read_both_metrics_of_every_method(tmp_path):
    rows = [{"method": "firp", "repeat": r, "test_balanced_accuracy": 0.8 + 0.02 * r,
             "test_balanced_accuracy_valid_threshold": 0.85} for r in range(2)]
    rows.append({"method": "dvd", "repeat": 0})  # not run: no scores
    record = tmp_path / "protocol.json"
    record.write_text(json.dumps({"rows": rows}))
    assert protocol_thresholds(record) == {"firp": {"repeats": 2, "at_0.5": pytest.approx(0.81),
                                                    "at_validation_threshold": pytest.approx(0.85)}}


def test_the_analysis_reads_a_recorded_dataset(tiny_dataset, tmp_path):
    out = tmp_path / "seeds.json"
    argv = ["--data", str(tiny_dataset), "--repeats", "2", "--seeds", "3", "--out", str(out)]
    assert main(argv) == 0
    result = json.loads(out.read_text())
    assert result["episodes"] == 20 and result["command"] == "python -m experiments.description_seeds " + " ".join(argv)
    assert result["summary"]["one seed, threshold 0.5"]["n"] == 6  # 2 repeats x 3 seeds
    assert result["summary"]["best of 3 seeds, validation threshold"]["n"] == 2
    assert all(0.0 <= s["min"] <= s["mean"] <= s["max"] <= 1.0 for s in result["summary"].values())


@pytest.mark.parametrize("flag, value, rule", [("--seeds", "4", "multiple of 3"), ("--repeats", "0", "at least 1"),
                                               ("--protocol", "missing.json", "no such record")])
def test_bad_arguments_name_the_flag_and_the_rule(tiny_dataset, tmp_path, capsys, flag, value, rule):
    with pytest.raises(SystemExit) as stop:
        main(["--data", str(tiny_dataset), "--out", str(tmp_path / "x.json"), flag, str(tmp_path / value)
              if flag == "--protocol" else value])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert flag in err and rule in err


def test_a_training_share_is_stratified_nested_and_fixed_per_split():
    from experiments.description_seeds import training_share
    labels = np.array([True] * 60 + [False] * 20)
    train = np.arange(0, 80, 1)[::2]  # 30 successes, 10 failures
    half, quarter = training_share(labels, train, 0.5, 0), training_share(labels, train, 0.25, 0)
    assert set(half) <= set(train) and set(quarter) <= set(half)
    assert labels[half].sum() == 15 and (~labels[half]).sum() == 5
    assert list(training_share(labels, train, 0.5, 0)) == list(half)
    assert list(training_share(labels, train, 0.5, 1)) != list(half)
    assert list(training_share(labels, train, 1.0, 0)) == list(train)
    assert (~labels[training_share(labels, train, 0.01, 0)]).sum() == 1  # every class keeps an episode


@pytest.mark.slow
def test_the_learning_curve_ends_at_the_full_study_and_is_drawn(tiny_dataset, tmp_path):
    out, plot = tmp_path / "curve.json", tmp_path / "curve.png"
    assert main(["--data", str(tiny_dataset), "--repeats", "2", "--seeds", "3", "--out", str(tmp_path / "full.json")]) == 0
    assert main(["--data", str(tiny_dataset), "--repeats", "2", "--seeds", "3", "--fractions", "0.5",
                 "--target", "0.9", "--plot", str(plot), "--out", str(out)]) == 0
    full, result = json.loads((tmp_path / "full.json").read_text()), json.loads(out.read_text())
    assert [p["fraction"] for p in result["curve"]] == [0.5, 1.0] and result["target"] == 0.9
    assert result["curve"][-1]["summary"] == full["summary"] == result["summary"]
    assert result["curve"][0]["train_episodes"] < result["curve"][1]["train_episodes"]
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("extra, rule", [(["--fractions", "0"], "strictly between 0 and 1"),
                                         (["--fractions", "1.5"], "strictly between 0 and 1"),
                                         (["--fractions", "0.5", "0.5"], "each share once"),
                                         (["--plot", "c.png"], "needs --fractions"),
                                         (["--target", "0.9"], "needs --fractions")])
def test_bad_curve_flags_name_the_flag_and_the_rule(tiny_dataset, tmp_path, capsys, extra, rule):
    with pytest.raises(SystemExit) as stop:
        main(["--data", str(tiny_dataset), "--out", str(tmp_path / "x.json"), *extra])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert extra[0] in err and rule in err
