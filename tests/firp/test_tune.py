"""Tuning end to end on a micro-dataset: study → top trials → bundle → load → score (the CI path)."""

import numpy as np
import optuna

from firp.bundle import load_bundle
from firp.serving import EnsembleScorer
from firp.core.episodes import EpisodeDataset
from firp.tune import SPACES, main, top_trials


def test_tune_export_load_score(tiny_dataset, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    storage = f"sqlite:///{tmp_path / 'study.db'}"
    argv = ["--data", str(tiny_dataset), "--trials", "3", "--epochs", "2", "--threads", "1", "--image-size", "32",
            "--storage", storage, "--cache-dir", str(tmp_path / "cache"), "--no-progress", "--space", "paper"]
    assert main(argv) == 0
    study = optuna.load_study(study_name=f"firp-{tiny_dataset.stem}", storage=storage)
    assert len([t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]) == 3
    # asking for 4 trials resumes the study: one more, none repeated
    assert main([*argv[:3], "4", *argv[4:]]) == 0
    study = optuna.load_study(study_name=f"firp-{tiny_dataset.stem}", storage=storage)
    assert len(study.trials) == 4 and len(top_trials(study, 5)) == 4
    assert study.user_attrs["search_space"] == "paper"
    for t in study.trials:
        assert "prediction" not in t.params  # the paper keeps the one-step terms at weight 1
        assert t.params["lr"] in (1e-5, 1e-4, 3e-4, 1e-3) and t.params["alpha"] in (1e-3, 1e-2, 1e-1, 0.0)

    bundle_dir = tmp_path / "bundle"
    png = tmp_path / "report" / "reliability.png"
    assert main([*argv[:3], "0", *argv[4:], "--export", str(bundle_dir), "--reliability", str(png)]) == 0
    bundle = load_bundle(bundle_dir)
    assert len(bundle.models) == 4 and 0.0 <= bundle.threshold <= 1.0
    assert png.stat().st_size > 0 and not list(tmp_path.glob("*_reliability.png"))  # nothing beside the bundle
    with EpisodeDataset(tiny_dataset) as ds:
        image, plan = ds.frames(0)[0], ds.actions(0)
    result = EnsembleScorer(bundle).score(image, np.stack([plan, plan]))
    assert result.probabilities.shape == (2,) and np.all((0 <= result.probabilities) & (result.probabilities <= 1))
    assert result.member_probabilities.shape == (4, 2)
    np.testing.assert_allclose(result.probabilities[0], result.probabilities[1], atol=1e-6)


def test_product_space_also_tunes_the_prediction_weight(tiny_dataset, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    storage = f"sqlite:///{tmp_path / 'study.db'}"
    assert main(["--data", str(tiny_dataset), "--trials", "2", "--epochs", "1", "--threads", "1", "--image-size", "32",
                 "--storage", storage, "--cache-dir", str(tmp_path / "cache"), "--no-progress",
                 "--report", str(tmp_path / "study.md")]) == 0
    report = (tmp_path / "study.md").read_text()
    assert "Search space `product`" in report and report.count("\n| ") == 3  # header + two trials
    study = optuna.load_study(study_name=f"firp-{tiny_dataset.stem}", storage=storage)
    assert study.user_attrs["search_space"] == "product"
    for t in study.trials:
        assert t.params["prediction"] in SPACES["product"]["prediction"]
        assert t.params["lr"] in SPACES["product"]["lr"]
