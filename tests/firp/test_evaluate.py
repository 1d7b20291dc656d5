"""The evaluation protocol end to end on a synthetic recorded dataset (real HDF5, real backbone)."""

import json

import numpy as np
import pytest

from firp.contract import make_plan
from firp.episodes import EpisodeRecord, consolidate, write_episode_part
from firp.evaluate import main, split_indices

T = 10


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("evaldata")
    rng = np.random.default_rng(0)
    for i in range(20):
        success = bool(i % 2)
        frames = rng.integers(0, 255, (T, 32, 32, 3), dtype=np.uint8)
        frames[:, :8, :8] = 255 if success else 0  # the image tells the label apart
        targets = np.tile([0, 0, 0, -1.5, 0, 1.5, 0, 0.02, 0.02], (T, 1)) + rng.normal(0, 0.001, (T, 9))
        plan = make_plan(np.arange(T) % 7, targets).astype(np.float32)
        write_episode_part(root / "parts", i, EpisodeRecord(frames, plan, np.zeros((T, 3)), success, {"seed": i}))
    consolidate(root / "parts", root / "tiny.h5", {"fps": 4, "T": T, "task": "stacking"})
    return root / "tiny.h5"


def test_splits_are_disjoint_stratified_and_cover_everything():
    labels = np.array([0, 1] * 50)
    train, valid, test = split_indices(labels, repeat=0)
    assert len(set(train) | set(valid) | set(test)) == 100
    assert not (set(train) & set(test)) and not (set(valid) & set(test)) and not (set(train) & set(valid))
    assert len(test) == 20 and labels[test].sum() == 10
    assert list(split_indices(labels, 0)[2]) == list(test) and list(split_indices(labels, 1)[2]) != list(test)


def test_protocol_writes_results_and_resumes(tiny_dataset, tmp_path):
    out = tmp_path / "eval"
    argv = ["--data", str(tiny_dataset), "--repeats", "1", "--methods", "a_mlp", "firp", "--epochs", "2",
            "--threads", "1", "--image-size", "32", "--out", str(out), "--cache-dir", str(tmp_path / "cache"),
            "--no-progress"]
    assert main(argv) == 0
    results = json.loads((out / "results.json").read_text())
    assert {r["method"] for r in results["rows"]} == {"a_mlp", "firp"}
    for r in results["rows"]:
        assert 0.0 <= r["test_balanced_accuracy"] <= 1.0 and r["n_test"] == 4
    assert "dvd" in results["not_run"] and "| a_mlp |" in (out / "results.md").read_text()
    # a second call finds every (repeat, method) done and trains nothing
    before = (out / "r0-firp.json").stat().st_mtime_ns
    assert main(argv) == 0
    assert (out / "r0-firp.json").stat().st_mtime_ns == before


def test_missing_dataset_is_a_clear_cli_error(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--data", str(tmp_path / "nope.h5")])
    assert "--data:" in capsys.readouterr().err
