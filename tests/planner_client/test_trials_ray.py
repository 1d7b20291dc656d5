"""The main job's trials on Ray actors (a real local cluster of 2 CPUs, the real scoring service on
loopback): records equal a sequential run's, stay in trial order and resume; a killed actor costs a
retry, never a lost or doubled trial; the command line launches no sim worker for them and refuses
what does not run there, naming the flag."""

from __future__ import annotations

import os
import signal

import pytest

from planner_client.__main__ import main
from planner_client.embedded import EmbeddedSim
from planner_client.launcher import Launcher
from planner_client.loop import RunConfig, RunSetupError, read_records, run_identity, run_trials
from planner_client.ray_trials import RayTrials, trials_on_ray
from planner_client.tamp import PlannerConfig, TampPlanner

from .records import assert_same_trials

pytestmark = pytest.mark.slow  # make test-fast leaves this module out

ray = pytest.importorskip("ray", reason="the ray extra is not installed")

T = 16  # inside the tiny bundle's T range (8, 16)


@pytest.fixture(scope="module")
def tiny_bundle(tmp_path_factory):
    import torch

    from tests.firp.bundle_helpers import export_tiny

    torch.manual_seed(0)
    return export_tiny(tmp_path_factory.mktemp("bundle") / "tiny")


@pytest.fixture(scope="module")
def scorer(tiny_bundle, tmp_path_factory):
    with Launcher(tmp_path_factory.mktemp("service"), bundle=tiny_bundle, sim=False, ready_timeout=120) as services:
        with services.score_client() as client:
            yield client


@pytest.fixture(scope="module")
def sim():
    world = EmbeddedSim()
    yield world
    world.close()


def test_trials_on_ray_equal_a_sequential_run_in_order_and_resume(tmp_path, scorer, sim):
    planner = TampPlanner(PlannerConfig(horizon=T))
    config = dict(trials=4, max_iterations=3, threshold=0.5, seed=20)
    sequential = list(run_trials(RunConfig(out=tmp_path / "seq.jsonl", **config), sim, planner, scorer))
    on_ray = RayTrials("local", actors=2, service_url=scorer.base_url)
    list(run_trials(RunConfig(out=tmp_path / "ray.jsonl", **{**config, "trials": 2}), None, planner, scorer,
                    ray=on_ray))
    assert not ray.is_initialized()  # the private cluster stopped with the run
    resumed = list(run_trials(RunConfig(out=tmp_path / "ray.jsonl", resume=True, **config), None, planner, scorer,
                              ray=on_ray))
    assert [r["trial"] for r in resumed] == [2, 3]
    records = read_records(tmp_path / "ray.jsonl")
    assert [r["trial"] for r in records] == [0, 1, 2, 3]
    assert_same_trials(records, sequential)
    assert all("firp_success" in r for r in records) and len({r["request_id"] for r in records}) == 4


def test_a_killed_actor_costs_a_retry_never_a_lost_or_doubled_trial(tmp_path, sim):
    planner = TampPlanner(PlannerConfig(horizon=T))
    config = RunConfig(out=tmp_path / "run.jsonl", trials=4, max_iterations=2, seed=40)
    sequential = list(run_trials(RunConfig(out=tmp_path / "seq.jsonl", trials=4, max_iterations=2, seed=40), sim,
                                 planner))
    actors: list = []
    killed: list[int] = []
    records = []
    for record in trials_on_ray(RayTrials("local", actors=2), list(range(4)), config=config, planner=planner,
                                identity=run_identity(config, planner, None), decision=None,
                                on_actors=actors.extend):
        records.append(record)
        if not killed:  # the first actor still has a trial running or queued (two in flight per actor)
            pid = ray.get(actors[0].pid.remote())
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
    assert killed and [r["trial"] for r in records] == [0, 1, 2, 3]
    assert_same_trials(records, sequential)


def test_cli_runs_trials_on_ray_with_a_launched_service_and_no_sim_worker(tmp_path, tiny_bundle):
    out = tmp_path / "runs" / "run.jsonl"
    assert main(["run", "--trials", "3", "--horizon", str(T), "--max-iterations", "2", "--threshold", "1.01",
                 "--bundle", str(tiny_bundle), "--out", str(out), "--seed", "5", "--parallel", "2",
                 "--ray", "local"]) == 0
    records = read_records(out)
    assert [r["trial"] for r in records] == [0, 1, 2] and [r["seed"] for r in records] == [5, 6, 7]
    assert all(r["firp_iterations"] == 2 for r in records)  # 1.01 accepts nothing: both candidates scored
    assert {p.name for p in (out.parent / "logs").iterdir()} == {"service.log"}


@pytest.mark.parametrize("extra, message", [
    (["--ray", " "], "--ray: give local, auto or a cluster address"),
    (["--ray", "local", "--sim", "http://127.0.0.1:9"], "--ray: the trials run our world inside the Ray actors"),
    (["--ray", "local", "--record", "rec"], "--record writes the executions on this machine's disk"),
    (["--ray", "10.0.0.5:6379"], "--ray 10.0.0.5:6379: the actors on the cluster's nodes call the scoring service"),
    (["--ray", "local", "--world", "robosuite"], "--ray: only our world (--world mujoco) runs inside Ray actors"),
])
def test_cli_refuses_what_does_not_run_on_ray_naming_the_flag(tmp_path, capsys, extra, message):
    with pytest.raises(SystemExit) as exit_:
        main(["run", "--trials", "1", "--out", str(tmp_path / "r.jsonl"), *extra])
    assert exit_.value.code == 2 and message in capsys.readouterr().err


def test_run_trials_refuses_recording_on_ray(tmp_path):
    config = RunConfig(out=tmp_path / "r.jsonl", trials=1, record=tmp_path / "rec")
    with pytest.raises(RunSetupError, match="--record"):
        next(run_trials(config, None, TampPlanner(PlannerConfig(horizon=T)), ray=RayTrials("local", 1)))
