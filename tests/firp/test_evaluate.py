"""The evaluation protocol end to end on a synthetic recorded dataset (real HDF5, real backbone)."""

import json

import numpy as np
import pytest

from firp.evaluate import main, split_indices

pytestmark = pytest.mark.slow  # make test-fast leaves this module out



def test_splits_are_disjoint_stratified_and_cover_everything():
    labels = np.array([0, 1] * 50)
    train, valid, test = split_indices(labels, repeat=0)
    assert len(set(train) | set(valid) | set(test)) == 100
    assert not (set(train) & set(test)) and not (set(valid) & set(test)) and not (set(train) & set(valid))
    assert len(test) == 20 and labels[test].sum() == 10
    assert list(split_indices(labels, 0)[2]) == list(test) and list(split_indices(labels, 1)[2]) != list(test)


def test_protocol_writes_results_and_resumes(tiny_dataset, tmp_path):
    out = tmp_path / "eval"
    argv = ["--data", str(tiny_dataset), "--repeats", "1", "--methods", "a_mlp", "firp", "firp_tcr", "--epochs", "2",
            "--threads", "1", "--image-size", "32", "--out", str(out), "--cache-dir", str(tmp_path / "cache"),
            "--no-progress"]
    assert main(argv) == 0
    results = json.loads((out / "results.json").read_text())
    assert {r["method"] for r in results["rows"]} == {"a_mlp", "firp", "firp_tcr", "firp_ensemble"}
    singles = {r["method"]: r for r in results["rows"] if r["method"] != "firp_ensemble"}
    for r in singles.values():
        assert 0.0 <= r["test_balanced_accuracy"] <= 1.0 and r["n_test"] == 4 and len(r["test_scores"]) == 4
    (ens,) = [r for r in results["rows"] if r["method"] == "firp_ensemble"]
    assert ens["members"] == ["firp", "firp_tcr"] and 0.0 <= ens["test_balanced_accuracy"] <= 1.0
    # the ensemble's scores are the members' mean: recompute its balanced accuracy from the rows
    from firp.metrics import balanced_accuracy
    mean = (np.array(singles["firp"]["test_scores"]) + np.array(singles["firp_tcr"]["test_scores"])) / 2
    from firp.core.episodes import EpisodeDataset
    with EpisodeDataset(tiny_dataset) as ds:
        y = ds.success_labels()[singles["firp"]["test_index"]].astype(bool)
    assert ens["test_balanced_accuracy"] == pytest.approx(balanced_accuracy(y, mean >= 0.5))
    assert "firp_ensemble − best non-oracle baseline (a_mlp)" in (out / "results.md").read_text()
    # a dataset of no named world is judged by our own world's bar
    assert results["env"] is None and "(target ≥ +0.05:" in (out / "results.md").read_text()
    assert "dvd" in results["not_run"] and "| a_mlp |" in (out / "results.md").read_text()
    # a second call finds every (repeat, method) done and trains nothing
    before = (out / "r0-firp.json").stat().st_mtime_ns
    assert main(argv) == 0
    assert (out / "r0-firp.json").stat().st_mtime_ns == before


def test_only_repeats_trains_its_share_and_summarises_all(tiny_dataset, tmp_path, capsys):
    out = tmp_path / "eval"
    common = ["--data", str(tiny_dataset), "--repeats", "2", "--methods", "a_mlp", "--epochs", "1", "--threads", "1",
              "--image-size", "32", "--out", str(out), "--cache-dir", str(tmp_path / "cache"), "--no-progress"]
    assert main([*common, "--only-repeats", "1"]) == 0
    assert not (out / "r0-a_mlp.json").exists() and (out / "r1-a_mlp.json").exists()
    # the record's command reproduces the repeats its table covers
    assert "--repeats 2 --only-repeats 1 --methods" in json.loads((out / "results.json").read_text())["command"]
    assert main([*common, "--only-repeats", "0"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert [r["repeat"] for r in results["rows"]] == [0, 1] and "--only-repeats" not in results["command"]
    with pytest.raises(SystemExit):
        main([*common, "--only-repeats", "2"])
    assert "--only-repeats: every index must be < --repeats (2)" in capsys.readouterr().err


def test_the_summary_counts_repeats_another_process_finished_meanwhile(tiny_dataset, tmp_path, monkeypatch):
    import shutil

    from firp import evaluate

    common = ["--data", str(tiny_dataset), "--repeats", "2", "--methods", "a_mlp", "--epochs", "1", "--threads", "1",
              "--image-size", "32", "--cache-dir", str(tmp_path / "cache"), "--no-progress"]
    elsewhere, out = tmp_path / "other", tmp_path / "eval"
    assert main([*common, "--out", str(elsewhere), "--only-repeats", "1"]) == 0
    train = evaluate.evaluate_method

    def train_while_the_other_finishes(*args, **kwargs):
        row = train(*args, **kwargs)
        shutil.copy(elsewhere / "r1-a_mlp.json", out / "r1-a_mlp.json")  # the process of repeat 1 ends first
        return row

    monkeypatch.setattr(evaluate, "evaluate_method", train_while_the_other_finishes)
    assert main([*common, "--out", str(out), "--only-repeats", "0"]) == 0
    assert [r["repeat"] for r in json.loads((out / "results.json").read_text())["rows"]] == [0, 1]


def test_missing_dataset_is_a_clear_cli_error(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--data", str(tmp_path / "nope.h5")])
    assert "--data:" in capsys.readouterr().err


def test_plan_geometry_protocol_and_the_geometry_only_yardstick(tiny_dataset, tmp_path, capsys):
    out = tmp_path / "eval"
    common = ["--data", str(tiny_dataset), "--repeats", "1", "--epochs", "1", "--threads", "1", "--image-size", "32",
              "--out", str(out), "--cache-dir", str(tmp_path / "cache"), "--no-progress"]
    with pytest.raises(SystemExit):
        main([*common, "--methods", "geometry_mlp", "--no-plan-geometry"])
    assert "geometry_mlp reads the plan's description or events" in capsys.readouterr().err
    assert main([*common, "--methods", "geometry_mlp", "firp_tcr"]) == 0  # the product preset reads it
    results = json.loads((out / "results.json").read_text())
    assert results["preset"] == "product" and results["overrides"] == {"epochs": 1, "image_size": 32}
    assert "--preset product --epochs 1 --image-size 32" in results["command"]
    rows = {r["method"]: r for r in results["rows"]}
    assert rows["geometry_mlp"]["config"]["model"]["baseline"]["plan_pooling"] == "none"
    assert rows["firp_tcr"]["config"]["model"]["geometry"]["enabled"] is True
    assert "best non-oracle baseline (geometry_mlp)" in (out / "results.md").read_text()


def test_presets_and_flags_make_one_recipe():
    """A run is its preset plus the flags given; ``paper`` is the dataclass defaults, ``product`` what ships."""
    import argparse

    from firp.flags import add_loss_flags, add_model_flags, add_training_flags, recipe_flags, recipe_from
    from firp.model.config import FIRPConfig
    from firp.presets import PRESETS
    from firp.train import TrainConfig

    parser = argparse.ArgumentParser()
    add_training_flags(parser)
    add_model_flags(parser)
    add_loss_flags(parser)
    paper, none = recipe_from(parser.parse_args(["--data", "x", "--preset", "paper", "--threads", "1"]))
    assert none == {} and paper.model == FIRPConfig() and paper == TrainConfig(threads=1)
    product, overrides = recipe_from(parser.parse_args(["--data", "x", "--no-plan-geometry", "--epochs", "100",
                                                        "--lambda", "0.0"]))
    assert overrides == {"epochs": 100, "plan_geometry": False, "overshooting": 0.0}
    assert product.epochs == 100 and not product.model.geometry.enabled and product.model.loss.overshooting == 0.0
    assert product.model.action_chunk == PRESETS["product"].train.model.action_chunk == 8
    assert recipe_flags("product", overrides) == "--preset product --epochs 100 --no-plan-geometry --lambda 0.0"
    generic, none = recipe_from(parser.parse_args(["--data", "x", "--preset", "generic"]))
    assert none == {} and generic.model.events.enabled and not generic.model.geometry.enabled
    assert generic.model.action_chunk == product.model.action_chunk  # product, but for how it reads the plan
    events, overrides = recipe_from(parser.parse_args(["--data", "x", "--plan-events", "--plan-view"]))
    assert events.model.events.enabled and events.model.events.view and not events.model.geometry.enabled
    with pytest.raises(ValueError, match="not both"):
        recipe_from(parser.parse_args(["--data", "x", "--plan-events", "--plan-geometry"]))
    with pytest.raises(ValueError, match="--plan-view"):
        recipe_from(parser.parse_args(["--data", "x", "--preset", "paper", "--plan-view"]))


def test_runs_as_ray_tasks_equal_the_sequential_run(tiny_dataset, tmp_path):
    pytest.importorskip("ray", reason="the ray extra is not installed")
    common = ["--data", str(tiny_dataset), "--repeats", "2", "--methods", "a_mlp", "firp", "--epochs", "2",
              "--threads", "1", "--image-size", "32", "--cache-dir", str(tmp_path / "cache"), "--no-progress"]
    assert main([*common, "--out", str(tmp_path / "sequential")]) == 0
    assert main([*common, "--out", str(tmp_path / "ray"), "--ray", "local"]) == 0

    def rows(name: str) -> list[dict]:
        out = json.loads((tmp_path / name / "results.json").read_text())["rows"]
        return [{k: v for k, v in row.items() if k != "train_seconds"} for row in out]

    sequential, on_ray = rows("sequential"), rows("ray")
    assert [(r["repeat"], r["method"]) for r in on_ray] == [(r["repeat"], r["method"]) for r in sequential]
    assert on_ray == sequential  # every score, threshold and metric, in protocol order


def test_the_bar_over_the_best_baseline_follows_the_datasets_world():
    from firp.evaluate import target_line, target_margin
    assert target_margin("robosuite") == 0.02 and target_margin("firp-mujoco-panda") == 0.05
    assert target_margin(None) == 0.05
    rows = [{"method": "gru", "test_balanced_accuracy": 0.86}, {"method": "firp_ensemble", "test_balanced_accuracy": 0.89},
            {"method": "oracle", "test_balanced_accuracy": 0.99}]
    assert target_line(rows, 0.02) == "firp_ensemble − best non-oracle baseline (gru) = +0.030 (target ≥ +0.02: met)"
    assert target_line(rows, 0.05).endswith("(target ≥ +0.05: not met)")


def test_the_generic_preset_on_a_set_of_mostly_initial_frames(tiny_dataset, tmp_path):
    """``firp collect --framed`` data end to end: the events read through the dataset's chain, every model on the
    same splits, the Oracle on the framed episodes of each split only."""
    from firp.core.episodes import EpisodeDataset, consolidate, write_episode_part
    from tests.firp.model.test_plan_events import PANDA

    with EpisodeDataset(tiny_dataset) as ds:
        for i, name in enumerate(ds.demo_names):
            record = ds.episode(name)
            if i % 2:
                record.frames = record.frames[:1].copy()
            write_episode_part(tmp_path / "parts", i, record)
    data = tmp_path / "mixed.h5"
    consolidate(tmp_path / "parts", data, {"fps": 4, "T": 10, "task": "stacking", "kinematics": PANDA})
    out = tmp_path / "eval"
    assert main(["--data", str(data), "--preset", "generic", "--repeats", "1", "--epochs", "1", "--threads", "1",
                 "--image-size", "32", "--methods", "geometry_mlp", "firp", "oracle", "--out", str(out),
                 "--cache-dir", str(tmp_path / "cache"), "--no-progress", "--device", "cpu"]) == 0
    rows = {r["method"]: r for r in json.loads((out / "results.json").read_text())["rows"]}
    assert rows["firp"]["config"]["model"]["events"]["kinematics"] == PANDA
    assert rows["firp"]["n_test"] == 4 and rows["oracle"]["n_test"] == 2  # the framed half of the test split
    assert all(i % 2 == 0 for i in rows["oracle"]["test_index"] + rows["oracle"]["valid_index"])
