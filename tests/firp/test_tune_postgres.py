"""Tuning on PostgreSQL: several `firp tune` workers on one study, against a real server (Debian's
package, started for these tests in a temporary directory). No trial is lost or done twice, a study
stops at its total whatever the number of workers, a dead worker's trial is retried under its own
seed and checkpoints, and any worker exports the top-five bundle."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import optuna
import pytest

from firp import tune
from firp.bundle import load_bundle
from tests.postgres import postgres_binaries, postgres_server

pytestmark = pytest.mark.skipif(postgres_binaries() is None, reason="PostgreSQL's server is not installed "
                                "(`make system-deps` installs Debian's postgresql)")
ROOT = Path(__file__).resolve().parents[2]
COMPLETE = optuna.trial.TrialState.COMPLETE


@pytest.fixture(scope="module")
def postgres_url():
    with postgres_server() as url:
        yield url


def _argv(data: Path, tmp_path: Path, storage: str, study: str, trials: int) -> list[str]:
    return ["--data", str(data), "--trials", str(trials), "--epochs", "1", "--threads", "1", "--image-size", "32",
            "--storage", storage, "--study", study, "--cache-dir", str(tmp_path / "cache"), "--no-progress",
            "--space", "paper"]


def _complete(study: optuna.Study) -> list[optuna.trial.FrozenTrial]:
    return study.get_trials(states=(COMPLETE,))


@pytest.mark.slow
def test_two_workers_share_one_study_without_losing_or_repeating_a_trial(tiny_dataset, tmp_path, postgres_url):
    argv = _argv(tiny_dataset, tmp_path, postgres_url, "shared", trials=6)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    workers = [subprocess.Popen([sys.executable, "-m", "firp.tune", *argv], cwd=tmp_path, env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for _ in range(2)]
    outputs = [w.communicate(timeout=600)[0] for w in workers]
    assert [w.returncode for w in workers] == [0, 0], outputs

    study = optuna.load_study(study_name="shared", storage=tune.open_storage(postgres_url))
    done = _complete(study)
    # each worker stops once the study holds 6; one trial a worker had already begun may finish beyond
    assert 6 <= len(done) <= 7 and all(t.state == COMPLETE for t in study.trials), [t.state for t in study.trials]
    assert len({t.number for t in done}) == len(done)
    assert len({t.user_attrs["worker"] for t in done}) == 2  # both workers trained trials
    for t in done:  # every finished trial's weights where its record says, under its own seed
        assert (Path(t.user_attrs["checkpoint"]) / "best.safetensors").is_file()
        assert t.user_attrs["config"]["seed"] == t.number
    # each worker samples from its own seed: with one seed both would replay the same proposals
    assert len({tuple(sorted(t.params.items())) for t in done}) == len(done)

    # any worker exports the top-five bundle from the shared study
    assert tune.main([*argv[:3], "0", *argv[4:], "--export", str(tmp_path / "bundle")]) == 0
    bundle = load_bundle(tmp_path / "bundle")
    assert len(bundle.models) == min(tune.TOP_K, len(done))


def _dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_a_trial_of_a_dead_worker_on_this_host_is_retried_at_once(tiny_dataset, tmp_path, postgres_url, monkeypatch):
    monkeypatch.chdir(tmp_path)
    storage = tune.open_storage(postgres_url)
    study = optuna.create_study(study_name="crashed", storage=storage, direction="maximize")
    crashed = study.ask({"lr": optuna.distributions.CategoricalDistribution(tune.LEARNING_RATES)})
    crashed.set_user_attr("worker", f"{socket.gethostname()}:{_dead_pid()}")
    alive = study.ask()
    alive.set_user_attr("worker", f"{socket.gethostname()}:{os.getpid()}")  # this process: still running

    assert tune.main(_argv(tiny_dataset, tmp_path, postgres_url, "crashed", trials=1)) == 0
    study = optuna.load_study(study_name="crashed", storage=storage)
    states = {t.number: t.state for t in study.trials}
    assert states[crashed.number] == optuna.trial.TrialState.FAIL
    assert states[alive.number] == optuna.trial.TrialState.RUNNING  # a live worker's trial is left alone
    [retry] = _complete(study)
    assert retry.user_attrs["retry_of"] == crashed.number and retry.params["lr"] == crashed.params["lr"]
    assert retry.user_attrs["config"]["seed"] == crashed.number  # trains as the trial it repeats
    assert Path(retry.user_attrs["checkpoint"]).name == f"trial_{crashed.number:04d}"


def test_a_trial_whose_heartbeat_went_stale_is_retried_by_another_worker(tiny_dataset, tmp_path, postgres_url,
                                                                         monkeypatch):
    """A worker on another machine stopped beating: once its last beat is older than the grace period,
    the next worker to start a trial fails it and runs its retry (Optuna's heartbeat and
    RetryHeartbeatStaleTrialCallback). The last beat is moved an hour back instead of waiting."""
    import sqlalchemy as sa

    monkeypatch.chdir(tmp_path)
    storage = tune.open_storage(postgres_url)
    study = optuna.create_study(study_name="stale", storage=storage, direction="maximize")
    lost = study.ask({"lr": optuna.distributions.CategoricalDistribution(tune.LEARNING_RATES)})
    lost.set_user_attr("worker", "another-machine:4242")
    storage.record_heartbeat(lost._trial_id)
    with storage.engine.begin() as connection:
        moved = connection.execute(sa.text("UPDATE trial_heartbeats SET heartbeat = heartbeat - interval '1 hour' "
                                           "WHERE trial_id = :id"), {"id": lost._trial_id})
        assert moved.rowcount == 1

    assert tune.main(_argv(tiny_dataset, tmp_path, postgres_url, "stale", trials=1)) == 0
    study = optuna.load_study(study_name="stale", storage=storage)
    assert study.trials[lost.number].state == optuna.trial.TrialState.FAIL
    [retry] = _complete(study)
    assert optuna.storages.RetryHeartbeatStaleTrialCallback.retried_trial_number(retry) == lost.number
    assert retry.params["lr"] == lost.params["lr"] and retry.user_attrs["config"]["seed"] == lost.number


def test_postgresql_urls_are_served_by_psycopg_3():
    """``postgresql://`` names no driver; SQLAlchemy's default would be psycopg2, which is not installed."""
    import psycopg
    import sqlalchemy.exc

    with pytest.raises(sqlalchemy.exc.OperationalError) as error:  # nothing listens on port 1
        tune.open_storage("postgresql://nobody@127.0.0.1:1/none")  # port 1: refused at once
    assert isinstance(error.value.orig, psycopg.OperationalError)
