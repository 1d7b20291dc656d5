"""experiments/prediction_gap.py: FIRP's head on predicted, real and first-frame-only sequences."""

import json

import pytest
import torch

from experiments.tcr_ablation import find_checkpoints, load_model
from firp.data import load_sequences
from firp.evaluate import main as evaluate

from experiments import prediction_gap as gap


@pytest.fixture(scope="module")
def evaluated(tiny_dataset, tmp_path_factory):
    root = tmp_path_factory.mktemp("gap")
    argv = ["--data", str(tiny_dataset), "--repeats", "1", "--methods", "a_mlp", "firp", "firp_tcr", "--epochs", "2",
            "--threads", "1", "--image-size", "32", "--out", str(root / "eval"), "--cache-dir", str(root / "cache"),
            "--no-progress"]
    assert evaluate(argv) == 0
    return root


def test_recomputes_the_recorded_scores_and_reports_every_source(tiny_dataset, evaluated, capsys):
    out = evaluated / "gap.json"
    assert gap.main(["--data", str(tiny_dataset), "--eval-dir", str(evaluated / "eval"), "--cache-dir",
                     str(evaluated / "cache"), "--threads", "1", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    rows = {r["method"]: r for r in json.loads((evaluated / "eval" / "results.json").read_text())["rows"]}
    assert {r["method"] for r in result["per_run"]} == {"firp", "firp_tcr"}
    for run in result["per_run"]:
        assert run["max_abs_diff_to_recorded_scores"] < 1e-5
        assert run["predicted"]["test_balanced_accuracy"] == rows[run["method"]]["test_balanced_accuracy"]
        for source in gap.SOURCES:
            assert 0.0 <= run[source]["test_balanced_accuracy_valid_threshold"] <= 1.0
    (ens,) = result["ensemble"]
    assert ens["members"] == 2
    assert ens["predicted"]["test_balanced_accuracy"] == rows["firp_ensemble"]["test_balanced_accuracy"]
    assert result["best_baseline"] == "a_mlp"
    assert result["target"] == pytest.approx(rows["a_mlp"]["test_balanced_accuracy"] + 0.05)
    assert "| real |" in capsys.readouterr().out


def test_first_only_ignores_the_later_frames_and_real_reads_them(tiny_dataset, evaluated):
    (ckpt,) = find_checkpoints(evaluated / "eval", ("firp",))[0]
    model = load_model(ckpt)
    data = load_sequences(tiny_dataset, model.cfg.encoder, evaluated / "cache", progress=False)
    frames = data.features[torch.arange(len(data))].clone()  # (N, T, Db)
    frames[:, 1:] = torch.randn_like(frames[:, 1:]) * 5
    changed = type(data)(frames, data.actions, data.labels, data.dataset_hash, data.demo_names)
    assert gap.head_scores(model, data, "first_only") == pytest.approx(gap.head_scores(model, changed, "first_only"))
    assert gap.head_scores(model, data, "real") != pytest.approx(gap.head_scores(model, changed, "real"))


def test_an_evaluation_without_firp_runs_is_a_clear_error(tiny_dataset, tmp_path, capsys):
    assert gap.main(["--data", str(tiny_dataset), "--eval-dir", str(tmp_path), "--out", str(tmp_path / "x.json")]) == 2
    assert "--eval-dir: no finished FIRP runs" in capsys.readouterr().err
