"""The launcher with real subprocesses: logs, a killed sim worker restarted mid-trial, start-up
failures reported with the log's tail, and SIGTERM escalating to SIGKILL."""

from __future__ import annotations

import os
import signal
import sys
import time

import httpx
import pytest

from planner_client.launcher import Launcher
from planner_client.processes import ManagedServer, ServerStartError
from planner_client.tamp import PlannerConfig, TampPlanner
from planner_client.transport import RetryPolicy

FAST = RetryPolicy(attempts=3, base_delay=0.05)


def _kill(launcher: Launcher) -> None:
    process = launcher.sim_server.process
    os.kill(process.pid, signal.SIGKILL)
    process.wait(10)


def test_servers_log_under_the_run_directory(launcher):
    log = launcher.sim_server.log_path
    assert log.parent.name == "logs" and log.name == "sim_worker.log"
    assert "start sim_worker on port" in log.read_text()
    assert httpx.get(launcher.sim_url + "/readyz").status_code == 200
    assert launcher.sim_url.startswith("http://127.0.0.1:")


@pytest.mark.slow
def test_a_killed_sim_worker_is_restarted_and_the_trial_goes_on(launcher):
    """Mid-trial: the episode was started and executed once, then the worker is SIGKILLed. The next
    execution restarts the worker on a new port, re-creates the episode and gives the same label."""
    sim = launcher.sim(retry=FAST)
    try:
        episode = sim.start("stacking", 31)
        plan = TampPlanner(PlannerConfig(horizon=16)).plan("stacking", episode.observation).actions
        before = sim.execute(episode, plan)
        old_url, restarts = launcher.sim_url, launcher.sim_restarts
        _kill(launcher)
        after = sim.execute(episode, plan)
        assert (after.success, after.reason, after.final_blocks) == (before.success, before.reason, before.final_blocks)
        assert launcher.sim_restarts == restarts + 1 and launcher.sim_alive()
        assert launcher.sim_url != old_url and sim.client.base_url == launcher.sim_url
    finally:
        sim.close()


def test_restart_if_dead_only_restarts_a_dead_worker(launcher):
    assert launcher.restart_sim_if_dead() is False
    restarts = launcher.sim_restarts
    _kill(launcher)
    assert not launcher.sim_alive()
    assert launcher.restart_sim_if_dead() is True
    assert launcher.sim_restarts == restarts + 1
    assert httpx.get(launcher.sim_url + "/readyz").status_code == 200
    log = launcher.sim_server.log_path.read_text()
    assert log.count("start sim_worker on port") == launcher.sim_restarts + 1


def test_a_server_that_dies_at_start_is_reported_with_its_log(tmp_path):
    server = ManagedServer("broken", lambda port: [sys.executable, "-c",
                                                   "import sys; print('cannot load the bundle', file=sys.stderr); "
                                                   "sys.exit(3)"], tmp_path, ready_timeout=30)
    with pytest.raises(ServerStartError) as err:
        server.start()
    message = str(err.value)
    assert "broken exited with code 3" in message and "cannot load the bundle" in message
    assert str(tmp_path / "broken.log") in message


@pytest.mark.slow
def test_a_failing_service_stops_the_whole_launch(tmp_path):
    """A scoring service that cannot start (here: a bundle that does not exist, or no service
    package yet) fails the launch with its log, and the sim worker already spawned is stopped."""
    launcher = Launcher(tmp_path, bundle=tmp_path / "no-such-bundle", ready_timeout=20)
    with pytest.raises(ServerStartError) as err:
        launcher.start()
    # exiting is what a service should do; never turning ready is reported the same way
    assert "service exited with code" in str(err.value) or "service was not ready" in str(err.value)
    assert "service.log" in str(err.value)
    assert not launcher.sim_alive() and not launcher.service_server.alive()


def test_a_server_that_never_gets_ready_times_out_and_is_stopped(tmp_path):
    server = ManagedServer("sleepy", lambda port: [sys.executable, "-c", "import time; time.sleep(60)"], tmp_path,
                           ready_timeout=0.5)
    with pytest.raises(ServerStartError) as err:
        server.start()
    assert "sleepy was not ready at http://127.0.0.1:" in str(err.value) and "within 0.5 s" in str(err.value)
    assert not server.alive()


def test_stop_escalates_to_sigkill_when_sigterm_is_ignored(tmp_path):
    # the marker is assembled at run time so the log's header line (which shows the argv) cannot match it
    code = ("import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); print('SIGTERM ' + 'IGNORED', "
            "flush=True); time.sleep(60)")
    server = ManagedServer("stubborn", lambda port: [sys.executable, "-c", code], tmp_path, stop_timeout=0.5)
    server.spawn()
    process = server.process
    deadline = time.monotonic() + 20
    while "SIGTERM IGNORED" not in server.log_tail():
        assert time.monotonic() < deadline
        time.sleep(0.05)
    server.stop()
    assert process.returncode == -signal.SIGKILL  # SIGTERM was ignored: stop() had to escalate
