"""A tiny collection end to end: file layout, read-back, resume, and survival of a killed run."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from firp.core.contract import CATEGORIES, CONTRACT_VERSION, validate_plan
from firp.core.episodes import EpisodeDataset
from planner_client.__main__ import main as cli_main
from planner_client.collect import CollectConfig, collect, episode_order

pytestmark = pytest.mark.slow  # make test-fast leaves this module out

TINY = dict(horizon=24, image_size=24, workers=1)


def test_tiny_collection_reads_back(tmp_path):
    out = tmp_path / "stacking.h5"
    balance = collect(CollectConfig(task="stacking", episodes=2, out=out, **TINY), progress=False)
    assert balance["total"] == 2 and balance["success"] + balance["failure"] == 2
    with EpisodeDataset(out) as ds:
        assert ds.attrs["fps"] == 4 and ds.attrs["T"] == 24 and ds.attrs["task"] == "stacking"
        assert list(ds.attrs["categories"]) == list(CATEGORIES) and ds.attrs["contract_version"] == CONTRACT_VERSION
        assert ds.attrs["image_height"] == 24
        for name in ds.demo_names:
            frames = ds.frames(name)
            assert frames.shape == (24, 24, 24, 3) and frames.dtype == np.uint8
            validate_plan(ds.actions(name))
            attrs = ds.demo_attrs(name)
            assert attrs["task"] == "stacking" and len(attrs["block_order"]) == 3
            assert set(attrs["pose_estimates"]) == {"red", "green", "blue"}
            assert tuple(attrs["block_order"]) == episode_order(attrs["seed"])
    assert not (tmp_path / "stacking.h5.parts").exists()


def test_a_collection_keeps_frames_of_the_first_episodes_a_view_of_all_and_the_same_labels(tmp_path):
    """``--framed 1 --view-size 48``: episode 0 keeps every frame, episode 1 its initial frame alone; both keep the
    view, and the dataset the arm's kinematics and the camera's calibration. Rendering changes no outcome: the
    labels and plans equal a collection that keeps every frame."""
    from firp.core.camera import CameraCalibration
    from firp.core.kinematics import KinematicChain

    out, full = tmp_path / "mixed.h5", tmp_path / "full.h5"
    collect(CollectConfig(task="stacking", episodes=2, out=out, framed=1, view_size=48, final_view=True, **TINY),
            progress=False)
    collect(CollectConfig(task="stacking", episodes=2, out=full, **TINY), progress=False)
    with EpisodeDataset(out) as ds, EpisodeDataset(full) as reference:
        assert ds.framed_mask().tolist() == [True, False] and ds.has_view
        assert ds.frames(1).shape == (1, 24, 24, 3) and ds.view(1).shape == (48, 48, 3)
        assert ds.has_final_view and ds.final_view(0).shape == (48, 48, 3)
        assert not np.array_equal(ds.final_view(0), ds.view(0))  # the scene after the plan ran
        np.testing.assert_array_equal(ds.frames(1)[0], reference.frames(1)[0])  # the same initial image
        np.testing.assert_array_equal(ds.success_labels(), reference.success_labels())
        for name in ds.demo_names:
            np.testing.assert_array_equal(ds.actions(name), reference.actions(name))
        attrs = ds.attrs
        assert attrs["framed_episodes"] == 1 and attrs["view_size"] == 48 and "kinematics" not in reference.attrs
        assert len(KinematicChain.from_dict(attrs["kinematics"])) == 7
        assert CameraCalibration.from_dict(attrs["camera_calibration"]).width == 24


def test_collection_resumes_without_redoing_episodes(tmp_path):
    out = tmp_path / "replacement.h5"
    collect(CollectConfig(task="replacement", episodes=2, out=out, **TINY), progress=False)
    with EpisodeDataset(out) as ds:
        first = {n: ds.actions(n).copy() for n in ds.demo_names}
    balance = collect(CollectConfig(task="replacement", episodes=3, out=out, **TINY), progress=False)
    assert balance["new_episodes"] == 1 and balance["total"] == 3
    with EpisodeDataset(out) as ds:
        for name, actions in first.items():
            np.testing.assert_array_equal(ds.actions(name), actions)
    # asking again for what is there does nothing
    assert collect(CollectConfig(task="replacement", episodes=3, out=out, **TINY), progress=False)["new_episodes"] == 0


def test_killed_collection_resumes_and_loses_nothing(tmp_path):
    out = tmp_path / "killed.h5"
    args = ["collect", "--task", "stacking", "--episodes", "4", "--out", str(out), "--workers", "1",
            "-T", "24", "--image-size", "24", "--no-progress"]
    proc = subprocess.Popen([sys.executable, "-m", "planner_client", *args], start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    parts = Path(str(out) + ".parts")
    deadline = time.time() + 120
    while time.time() < deadline and not (parts.exists() and any(parts.glob("demo_*.h5"))):
        time.sleep(0.1)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not out.exists(), "the final file must not exist before consolidation"
    done_before = len(list(parts.glob("demo_*.h5")))
    assert 1 <= done_before < 4
    assert cli_main(args) == 0
    with EpisodeDataset(out) as ds:
        assert len(ds) == 4
        assert sorted(ds.demo_attrs(n)["seed"] for n in ds.demo_names) == [0, 1, 2, 3]


@pytest.mark.parametrize("argv,message", [
    (["collect", "--task", "juggling", "--episodes", "1", "--out", "x.h5"], "invalid choice: 'juggling'"),
    (["collect", "--task", "stacking", "--episodes", "0", "--out", "x.h5"], "--episodes must be in [1,"),
    (["collect", "--task", "stacking", "--episodes", "2", "--out", "x.h5", "-T", "3"], "--horizon must be in"),
    (["collect", "--task", "stacking", "--episodes", "2", "--out", "x.h5", "--pose-error-mm", "-1"],
     "--pose-error-mm must be >= 0"),
    (["collect", "--task", "stacking", "--episodes", "2", "--out", "x.h5", "--camera", "workspaceview"],
     "--camera: our world's camera is fixed per task"),
])
def test_cli_rejects_bad_arguments_with_the_rule(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli_main(argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_the_sim_workers_old_collect_command_hands_over_to_the_planners(tmp_path):
    """``python -m sim_worker collect`` was the documented command; the sim worker imports no planner, so it
    runs ``python -m planner_client collect`` with the same arguments instead."""
    out = tmp_path / "old.h5"
    done = subprocess.run([sys.executable, "-m", "sim_worker", "collect", "--task", "replacement", "--episodes", "1",
                           "--out", str(out), "--workers", "1", "-T", "24", "--image-size", "24", "--no-progress"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "running python -m planner_client collect" in done.stderr
    with EpisodeDataset(out) as ds:
        assert len(ds) == 1 and ds.attrs["task"] == "replacement"
    bad = subprocess.run([sys.executable, "-m", "sim_worker", "collect", "--task", "juggling"], capture_output=True,
                         text=True, timeout=60)
    assert bad.returncode == 2 and "invalid choice: 'juggling'" in bad.stderr



def _odd_scenes_are_unplannable(index: int):
    from firp.core.contract import make_plan
    from firp.core.episodes import EpisodeRecord
    from planner_client.ik import IKFailure

    if index % 2:
        raise IKFailure(f"scene {index}: no choice is reachable")
    t = 24
    targets = np.tile([0.0, 0.0, 0.0, -1.5, 0.0, 1.5, 0.8, 0.04, 0.04], (t, 1))  # the Panda's ready posture
    return EpisodeRecord(frames=np.zeros((t, 8, 8, 3), np.uint8), actions=make_plan(np.zeros(t, int), targets),
                         states=np.zeros((t, 1)), success=index % 4 == 0, attrs={"seed": index})


def test_an_unplannable_scene_gives_no_episode_and_the_others_go_on(tmp_path):
    """A collection worker's step: an unplannable scene (IKFailure) writes nothing and says so (None);
    the driver lists it in the balance and a resume tries it again (its index has no part file)."""
    from firp.core.episodes import completed_indices
    from planner_client import collect as collect_module

    parts = tmp_path / "made-up.h5.parts"
    collect_module._pool_init(lambda: None, (), _odd_scenes_are_unplannable, parts)
    assert [collect_module._pool_collect_one(i) for i in range(4)] == [(0, True), (1, None), (2, False), (3, None)]
    assert completed_indices(tmp_path / "made-up.h5", parts) == {0, 2}
