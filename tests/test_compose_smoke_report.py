"""The compose smoke run's comparison (scripts/compose_smoke_report.py): it must catch a container
run whose scores, picks or outcomes differ from the same trials run without containers."""

from __future__ import annotations

import copy
import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("compose_smoke_report", ROOT / "scripts" / "compose_smoke_report.py")
report = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(report)


def _record(trial: int) -> dict:
    return {"trial": trial, "seed": 100_000 + trial, "task": "stacking",
            "run": {"model": {"name": "firp-stacking", "version": "abc"}},
            "firp_rule": "threshold", "firp_success": True, "firp_accepted": True, "firp_iterations": 2,
            "firp_order": ["green", "blue", "red"], "tamp_success": False, "oracle_success": True,
            "oracle_order": ["green", "blue", "red"],
            "rules": {"rank": {"order": ["green", "blue", "red"], "success": True}},
            "candidate_scores": {'["red", "green", "blue"]': 0.01, '["green", "blue", "red"]': 0.93}}


@pytest.fixture
def runs() -> tuple[list[dict], list[dict]]:
    host = [_record(i) for i in range(3)]
    return copy.deepcopy(host), host


def test_equal_runs_agree(runs):
    container, host = runs
    container[1]["candidate_scores"]['["green", "blue", "red"]'] += 4e-7  # inside the tolerance
    problems, largest = report.compare(container, host, trials=3)
    assert problems == [] and largest == pytest.approx(4e-7)


@pytest.mark.parametrize("change, names", [
    (lambda r: r["candidate_scores"].update({'["green", "blue", "red"]': 0.9301}), "score of"),
    (lambda r: r.update(firp_success=False), "firp_success"),
    (lambda r: r["rules"]["rank"].update(order=["red", "green", "blue"]), "rules"),
    (lambda r: r["run"]["model"].update(version="other"), "bundle"),
    (lambda r: r["candidate_scores"].pop('["red", "green", "blue"]'), "candidate_scores"),
])
def test_a_difference_names_the_trial_and_the_field(runs, change, names):
    container, host = runs
    change(container[2])
    problems, _ = report.compare(container, host, trials=3)
    assert len(problems) == 1 and problems[0].startswith("trial 2: ") and names in problems[0]


def test_a_missing_trial_is_a_difference(runs):
    container, host = runs
    problems, _ = report.compare(container[:2], host, trials=3)
    assert problems and "expected 3 trial records" in problems[0]


def _write(path: Path, records: list[dict]) -> Path:
    path.write_text("".join(json.dumps(r) + "\n" for r in records))
    return path


def test_main_writes_the_report_and_fails_on_a_difference(tmp_path, runs):
    container, host = runs
    args = ["--container", str(_write(tmp_path / "smoke.jsonl", container)), "--host", str(_write(tmp_path / "host.jsonl", host)),
            "--trials", "3", "--engine", "podman", "--base", "localhost/firp-base:bookworm",
            "--images", "service=1378:291", "sim_worker=1080:90", "--servers", "service=9.5:2:0", "--planner-seconds", "12", "--seconds", "600",
            "--out", str(tmp_path / "out")]
    assert report.main(args) == 1  # no summary next to the container run's records
    (tmp_path / "smoke.summary.json").write_text(json.dumps({"trials": 3}))
    assert report.main(args) == 0
    written = json.loads((tmp_path / "out" / "report.json").read_text())
    assert written["equal"] and written["scores_compared"] == 6 and written["planner_run_s"] == 12
    assert written["images"]["service"] == {"size_mb": 1378, "build_s": 291}
    assert written["servers"]["service"] == {"ready_s": 9.5, "stop_s": 2, "exit_code": 0}
    assert "| service | 1378 | 291 | 9.5 | 2 | 0 |" in (tmp_path / "out" / "report.md").read_text()
    container[0]["tamp_success"] = True
    _write(tmp_path / "smoke.jsonl", container)
    assert report.main(args) == 1
    assert json.loads((tmp_path / "out" / "report.json").read_text())["differences"] == ["trial 0: tamp_success True != False"]


def _collection(folder: Path, episodes: int, changed_pixel: bool = False) -> Path:
    """A tiny collection (T = 8, 16 px) of ``episodes`` episodes; ``changed_pixel`` alters one pixel of the last."""
    import numpy as np

    from firp.core.contract import make_plan
    from firp.core.episodes import EpisodeRecord, consolidate, write_episode_part

    rng = np.random.default_rng(0)
    for i in range(episodes):
        frames = rng.integers(0, 255, (8, 16, 16, 3), dtype=np.uint8)
        if changed_pixel and i == episodes - 1:
            frames[7, 15, 15, 0] ^= 1
        plan = make_plan(np.arange(8) % 7, np.tile([0, 0, 0, -1.5, 0, 1.5, 0, 0.02, 0.02], (8, 1))).astype(np.float32)
        write_episode_part(folder / "parts", i, EpisodeRecord(frames, plan, np.zeros((8, 3)), bool(i % 2), {"seed": i}))
    consolidate(folder / "parts", folder / "d.h5", {"fps": 4, "T": 8, "task": "stacking"})
    return folder / "d.h5"


def test_the_ray_collection_must_equal_the_one_without_containers(tmp_path):
    same = [_collection(tmp_path / name, 3) for name in ("ray", "host")]
    problems, facts = report.compare_datasets(*same)
    assert problems == [] and (facts["episodes"], facts["successes"]) == (3, 1)
    pixel = _collection(tmp_path / "pixel", 3, changed_pixel=True)
    assert "differs" in report.compare_datasets(pixel, same[1])[0][0]  # one pixel of one frame
    shorter = _collection(tmp_path / "shorter", 2)
    assert "2 episodes" in report.compare_datasets(shorter, same[1])[0][0]
    assert "no dataset" in report.compare_datasets(tmp_path / "missing.h5", same[1])[0][0]
