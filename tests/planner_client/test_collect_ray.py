"""Collection on a real local Ray cluster (2 CPUs): the same episodes as the process pool, bit for bit,
and a worker killed mid-run costs a retry, never a lost or doubled episode."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest

from firp.core.episodes import EpisodeDataset
from planner_client.__main__ import main as cli_main
from planner_client.collect import CollectConfig, collect

pytestmark = pytest.mark.slow  # make test-fast leaves this module out

ray = pytest.importorskip("ray", reason="the ray extra is not installed")

TINY = dict(horizon=24, image_size=24, workers=2)


def _episodes(path) -> dict[int, dict]:
    """Every episode's arrays and attrs, keyed by its seed."""
    out = {}
    with EpisodeDataset(path) as ds:
        for name in ds.demo_names:
            attrs = ds.demo_attrs(name)
            out[attrs["seed"]] = {"frames": ds.frames(name).copy(), "actions": ds.actions(name).copy(),
                                  "states": ds.states(name).copy(), "success": ds.success(name), "attrs": attrs}
    return out


def _assert_same(a: dict, b: dict) -> None:
    assert sorted(a) == sorted(b)
    for seed in a:
        for key in ("frames", "actions", "states"):
            np.testing.assert_array_equal(a[seed][key], b[seed][key], err_msg=f"seed {seed}: {key}")
        assert a[seed]["success"] == b[seed]["success"] and a[seed]["attrs"] == b[seed]["attrs"]


@pytest.fixture(scope="module")
def pool_episodes(tmp_path_factory):
    out = tmp_path_factory.mktemp("pool") / "stacking.h5"
    collect(CollectConfig(task="stacking", episodes=6, out=out, **TINY), progress=False)
    return _episodes(out)


def test_ray_episodes_are_bit_identical_to_the_process_pool(tmp_path, pool_episodes):
    out = tmp_path / "stacking.h5"
    assert cli_main(["collect", "--task", "stacking", "--episodes", "6", "--out", str(out), "--workers", "2",
                     "-T", "24", "--image-size", "24", "--ray", "local", "--no-progress"]) == 0
    _assert_same(_episodes(out), pool_episodes)
    assert not ray.is_initialized()  # the private cluster stopped with the run
    assert not out.with_name(out.name + ".parts").exists()


def test_a_killed_ray_worker_costs_a_retry_never_a_lost_or_doubled_episode(tmp_path, pool_episodes):
    out = tmp_path / "stacking.h5"
    killed: list[int] = []

    parts = out.with_name(out.name + ".parts")

    def kill_one(actors) -> None:
        """SIGKILL the first actor's process as soon as the first episode is written: it still has episodes
        queued or running then (6 episodes, 2 actors, 2 calls in flight on each)."""
        pid = ray.get(actors[0].pid.remote())

        def kill_after_first_episode() -> None:
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline and not any(parts.glob("*.h5")):
                time.sleep(0.01)
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

        threading.Thread(target=kill_after_first_episode, daemon=True).start()

    balance = collect(CollectConfig(task="stacking", episodes=6, out=out, **TINY), progress=False, ray="local",
                      on_actors=kill_one)
    assert killed and balance["total"] == 6 and balance["new_episodes"] == 6
    episodes = _episodes(out)
    assert len(episodes) == 6  # no episode doubled (6 demos for 6 seeds) and none lost
    _assert_same(episodes, pool_episodes)


def test_resume_on_ray_skips_finished_episodes(tmp_path, pool_episodes):
    out = tmp_path / "stacking.h5"
    collect(CollectConfig(task="stacking", episodes=3, out=out, **TINY), progress=False)
    balance = collect(CollectConfig(task="stacking", episodes=6, out=out, **TINY), progress=False, ray="local")
    assert balance["new_episodes"] == 3 and balance["total"] == 6
    _assert_same(_episodes(out), pool_episodes)


def test_an_empty_ray_address_is_refused_naming_the_flag(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        cli_main(["collect", "--task", "stacking", "--episodes", "1", "--out", str(tmp_path / "x.h5"), "--ray", " "])
    assert exc.value.code == 2 and "--ray: give local, auto or a cluster address" in capsys.readouterr().err
