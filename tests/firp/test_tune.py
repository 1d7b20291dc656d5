"""Tuning end to end on a micro-dataset: study → top trials → bundle → load → score (the CI path)."""

import numpy as np
import optuna

from firp.bundle import load_bundle
from firp.serving import EnsembleScorer
from firp.core.episodes import EpisodeDataset
from firp.tune import SPACES, main, top_trials
import pytest


@pytest.mark.slow
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


@pytest.mark.slow
def test_an_exported_bundle_carries_decision_evidence_that_certify_reproduces(tiny_dataset, tmp_path, monkeypatch):
    """The export measures the evidence on the training path's features; ``firp certify`` measures it again
    through the serving path and must find the same balanced accuracy (else it refuses)."""
    import json

    from firp.bundle.evidence import certify_bundle
    from firp.bundle.evidence import main as certify_main
    from firp.core.decisions import EVIDENCE_KEY

    monkeypatch.chdir(tmp_path)
    storage = f"sqlite:///{tmp_path / 'study.db'}"
    bundle_dir = tmp_path / "bundle"
    assert main(["--data", str(tiny_dataset), "--trials", "2", "--epochs", "2", "--threads", "1", "--image-size", "32",
                 "--storage", storage, "--cache-dir", str(tmp_path / "cache"), "--no-progress", "--space", "paper",
                 "--export", str(bundle_dir)]) == 0
    exported = json.loads((bundle_dir / "manifest.json").read_text())[EVIDENCE_KEY]
    low, high = exported["interval"]
    assert low <= exported["balanced_accuracy"] <= high and exported["informative"] == (low > 0.5)
    assert exported["n_successes"] + exported["n_failures"] == 4  # 20% of the 20 episodes
    assert len(exported["failure_scores"]) == exported["n_failures"]
    weights = sorted(p.name for p in bundle_dir.glob("*.safetensors"))

    certified = certify_bundle(bundle_dir, tiny_dataset, progress=False)
    assert certified["balanced_accuracy"] == exported["balanced_accuracy"]
    np.testing.assert_allclose(certified["failure_scores"], exported["failure_scores"], atol=1e-5)
    assert certified["dataset"]["is_training_data"] is True
    again = load_bundle(bundle_dir)  # the rewritten manifest still verifies; the weights are untouched
    assert again.manifest[EVIDENCE_KEY]["dataset"]["sha256"] == again.manifest["training_data"]["sha256"]
    assert sorted(p.name for p in bundle_dir.glob("*.safetensors")) == weights

    # another dataset: refused, naming the rule; nothing is rewritten
    other = tmp_path / "other.h5"
    other.write_bytes(tiny_dataset.read_bytes())
    import h5py

    with h5py.File(other, "a") as f:
        first = sorted(f["data"])[0]
        f["data"][first]["actions"][0, 8] += 1e-3  # another collection: other content, so another hash
    before = (bundle_dir / "manifest.json").read_bytes()
    assert certify_main(["--bundle", str(bundle_dir), "--data", str(other), "--no-progress"]) == 2
    assert (bundle_dir / "manifest.json").read_bytes() == before
