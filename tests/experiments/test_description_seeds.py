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
