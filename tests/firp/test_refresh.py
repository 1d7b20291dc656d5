"""``firp refresh`` end to end on tiny real datasets and real bundles (the pretrained backbone at 32 px):
recorded scenes held out whole, members retrained warm, the paired comparison deciding promotion both
ways, the refreshed bundle hot-swapped into a running service only when promoted; the paired statistic
on its own; bad input named."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from firp.bundle import load_bundle
from firp.core.bundle_format import bundle_version
from firp.core.contract import make_plan
from firp.core.decisions import paired_comparison
from firp.core.episodes import EpisodeRecord, consolidate, write_episode_part
from firp.refresh import EXIT_KEPT, main as refresh_main
from firp.tune import main as tune_main
from tests.firp.learnable import SIZE, T, learnable_dataset

pytestmark = pytest.mark.slow  # make test-fast leaves this module out

SCENES, CANDIDATES = 16, 3


def recorded_dataset(root: Path) -> Path:
    """What ``firp run --record`` writes for 16 scenes x 3 candidates: ``scene_id`` links a scene's
    candidates; the label shows in the image corner, as in the collected set."""
    rng = np.random.default_rng(7)
    for scene in range(SCENES):
        for place in range(CANDIDATES):
            success = bool((scene + place) % 2)
            frames = rng.integers(0, 256, (T, SIZE, SIZE, 3), dtype=np.uint8)
            frames[:, : SIZE // 2, : SIZE // 2] = 255 if success else 0
            targets = np.tile([0, 0, 0, -1.5, 0, 1.5, 0, 0.02, 0.02], (T, 1)) + rng.normal(0, 0.05, (T, 9))
            targets[:, 7:] = np.clip(targets[:, 7:], 0.0, 0.04)
            plan = make_plan(np.arange(T) * 7 // T, targets).astype(np.float32)
            attrs = {"seed": 300_000 + scene, "scene_id": f"stacking/{300_000 + scene}", "trial": scene,
                     "candidate_index": place, "recorded_by": "firp run --record"}
            write_episode_part(root / "parts", scene * 100 + place,
                               EpisodeRecord(frames, plan, np.zeros((T, 1)), success, attrs))
    consolidate(root / "parts", root / "executions.h5", {"fps": 4, "T": T, "task": "stacking"})
    return root / "executions.h5"


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # firp tune keeps its trials under ./runs


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("refresh")
    return {"collected": learnable_dataset(root / "collected", "image", n=48),
            "shuffled": learnable_dataset(root / "shuffled", "image", n=48, shuffle=True),
            "recorded": recorded_dataset(root / "recorded"), "cache": root / "cache"}


def _bundle(data: dict, source: str, out: Path, epochs: int) -> Path:
    storage = f"sqlite:///{out.parent / (out.name + '.db')}"
    assert tune_main(["--data", str(data[source]), "--trials", "1", "--epochs", str(epochs), "--threads", "1",
                      "--image-size", "32", "--storage", storage, "--cache-dir", str(data["cache"]), "--no-progress",
                      "--space", "paper", "--export", str(out), "--reliability", str(out.parent / "r.png")]) == 0
    return out


def _refresh(data: dict, bundle: Path, out: Path, *extra: str) -> tuple[int, dict]:
    report = out.parent / (out.name + ".json")
    code = refresh_main(["--bundle", str(bundle), "--data", str(data["collected"]), "--data", str(data["recorded"]),
                         "--out", str(out), "--threads", "1", "--cache-dir", str(data["cache"]), "--no-progress",
                         "--resamples", "500", "--report", str(report), *extra])
    return code, json.loads(report.read_text())


def test_a_bundle_that_cannot_tell_is_refreshed_promoted_and_swapped_into_the_running_service(data, tmp_path):
    from service.app import create_app
    from service.settings import ServiceSettings
    from tests.loopback import serve_on_loopback

    current = _bundle(data, "shuffled", tmp_path / "current", epochs=1)  # trained where nothing tells the label
    app = create_app(ServiceSettings(bundle=current, threads=1))
    with serve_on_loopback(app) as address:
        code, report = _refresh(data, current, tmp_path / "new", "--epochs", "12", "--lr", "0.003",
                                "--swap", f"http://{address}")
        import httpx

        served = httpx.get(f"http://{address}/v1/model").json()
    held = report["split"]["held_out_scenes"]
    assert held and all(s.startswith("stacking/3") for s in held)  # recorded scenes only, whole
    assert report["split"]["held_out"] == CANDIDATES * len(held)
    paired = report["paired"]
    assert paired["n_scenes"] == len(held) and paired["new_balanced_accuracy"] > paired["current_balanced_accuracy"]
    assert code == 0 and report["promoted"], report["why"]
    new = load_bundle(tmp_path / "new")
    assert new.manifest["extra"]["refresh"]["promoted"] is True
    assert new.manifest["decision_evidence"]["n_successes"] > 0
    assert report["swapped"]["version"] == bundle_version(new.path, new.manifest) == served["version"]
    assert report["new"]["version"] == served["version"] != report["current"]["version"]


def test_a_worse_refresh_keeps_the_current_bundle_and_says_why(data, tmp_path, capsys):
    current = _bundle(data, "collected", tmp_path / "current", epochs=12)
    # from scratch at a learning rate that cannot move it in one epoch: a random ensemble
    code, report = _refresh(data, current, tmp_path / "new", "--epochs", "1", "--lr", "1e-9", "--no-warm-start")
    assert code == EXIT_KEPT and not report["promoted"]
    assert report["paired"]["current_balanced_accuracy"] > report["paired"]["new_balanced_accuracy"]
    assert "KEPT the current bundle" in capsys.readouterr().out
    assert load_bundle(tmp_path / "new").manifest["extra"]["refresh"]["promoted"] is False


def test_refresh_needs_recorded_executions_and_existing_files(data, tmp_path, capsys):
    bundle = _bundle(data, "collected", tmp_path / "current", epochs=1)
    assert refresh_main(["--bundle", str(bundle), "--data", str(data["collected"]), "--out", str(tmp_path / "n"),
                         "--cache-dir", str(data["cache"]), "--no-progress"]) == 2
    assert "none of the datasets holds recorded executions" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        refresh_main(["--bundle", str(bundle), "--data", str(tmp_path / "missing.h5"), "--out", str(tmp_path / "n")])
    assert "--data: " in capsys.readouterr().err


def test_paired_comparison_resamples_whole_scenes_and_is_zero_for_the_same_scores():
    rng = np.random.default_rng(0)
    labels = np.tile([True, False, True], 20)
    groups = [f"s{i // 3}" for i in range(60)]
    same = rng.random(60)
    result = paired_comparison(labels, groups, new_scores=same, new_threshold=0.5, current_scores=same,
                               current_threshold=0.5, resamples=300)
    assert result["difference"] == 0.0 and result["interval"] == [0.0, 0.0] and result["n_scenes"] == 20
    perfect = labels.astype(float)
    better = paired_comparison(labels, groups, new_scores=perfect, new_threshold=0.5, current_scores=same,
                               current_threshold=0.5, resamples=300)
    assert better["new_balanced_accuracy"] == 1.0 and 0.0 < better["interval"][0] <= better["difference"]
    with pytest.raises(ValueError, match="successes and failures"):
        paired_comparison([True] * 3, ["a", "b", "c"], new_scores=[1, 1, 1], new_threshold=0.5,
                          current_scores=[0, 0, 0], current_threshold=0.5)


def test_held_out_scenes_come_whole_from_the_newest_recording_only():
    import torch

    from firp.data import SequenceData
    from firp.refresh import Pool, held_out_scenes

    # 4 collected episodes, then two recordings of 6 scenes x 2 candidates (one success, one failure each)
    scenes = [f"c{i}" for i in range(4)] + [f"r1/{i // 2}" for i in range(12)] + [f"r2/{i // 2}" for i in range(12)]
    labels = torch.tensor([i % 2 for i in range(28)], dtype=torch.float32)
    data = SequenceData(torch.zeros(28, 2, 3), torch.zeros(28, 2, 16), labels, "h", [str(i) for i in range(28)])
    pool = Pool(data, scenes, np.array([False] * 4 + [True] * 24), [], np.array([0] * 4 + [1] * 12 + [2] * 12))
    rest, held = held_out_scenes(pool, fraction=0.5, seed=0)
    held_scenes = {scenes[i] for i in held}
    assert held_scenes and all(s.startswith("r2/") for s in held_scenes)
    assert len(held) == 2 * len(held_scenes) and not held_scenes & {scenes[i] for i in rest}
    assert sorted([*rest, *held]) == list(range(28))
