"""``python -m service`` as an operator starts it: a real uvicorn process on loopback.

The service binds port 0 (the OS picks a free one, which nobody else can take between choosing it
and binding it) and the test reads the port from uvicorn's log line.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time

import httpx
import pytest

from tests.processes import ROOT, ServedProcess, clean_env

from .helpers import plan_list, png_b64

pytestmark = pytest.mark.slow  # make test-fast leaves this module out

SERVE = ["--host", "127.0.0.1", "--port", "0"]


def _env(**extra: str) -> dict[str, str]:
    return clean_env("FIRP_SERVICE_", OMP_NUM_THREADS="1", **extra)


def test_starts_from_the_environment_serves_and_stops_cleanly(tiny_bundle):
    with ServedProcess("service", [*SERVE, "--no-access-log"], _env(FIRP_SERVICE_BUNDLE=str(tiny_bundle)),
                       listen_timeout=120) as service:
        # uvicorn listens only after the lifespan loaded the bundle: ready at once
        assert httpx.get(f"{service.base}/readyz", timeout=10).status_code == 200
        r = httpx.post(f"{service.base}/v1/score", json={"image": png_b64(), "plan": plan_list()}, timeout=10)
        assert r.status_code == 200 and r.json()["model"]["name"] == "tiny"
    err = service.log
    # SIGTERM drains (nothing was in flight) and exits 0
    assert service.returncode == 0, err
    assert "ready: bundle tiny" in err and "drained in" in err and "Application shutdown complete" in err


def test_sigterm_drains_admitted_work_refuses_new_work_and_exits_0(tiny_bundle):
    """Eight clients keep the service busy; SIGTERM arrives. Every request it had admitted is answered
    200; readiness says 503 ``draining`` at once while the socket still accepts; requests after it are
    503 ``not_ready`` with Retry-After, never a reset connection; the process exits 0."""
    env = _env(FIRP_SERVICE_BUNDLE=str(tiny_bundle), FIRP_SERVICE_DRAIN_GRACE_S="10",
               # no shedding: this test is about the drain, and a loaded CI machine makes 0.25 s of queue quickly
               FIRP_SERVICE_MAX_QUEUE_WAIT_S="0")
    answers: list[tuple[float, float, int, str | None]] = []  # (sent at, answered at, status, rule)
    failures: list[str] = []
    stop = threading.Event()
    with ServedProcess("service", [*SERVE, "--no-access-log"], env, listen_timeout=120) as service:
        body = {"image": png_b64(), "plans": [plan_list(seed=s) for s in range(4)]}

        def client() -> None:
            with httpx.Client(base_url=service.base, timeout=30) as http:
                while not stop.is_set():
                    sent = time.monotonic()
                    try:
                        r = http.post("/v1/score/batch", json=body)
                    except httpx.TransportError as exc:  # the socket closed after the drain: stop
                        failures.append(f"{sent:.3f} {type(exc).__name__}")
                        return
                    rule = None if r.status_code == 200 else r.json()["error"]["rule"]
                    answers.append((sent, time.monotonic(), r.status_code, rule))
                    if r.status_code == 503:
                        assert r.headers["Retry-After"] == "1"

        threads = [threading.Thread(target=client) for _ in range(8)]
        try:
            for t in threads:
                t.start()
            time.sleep(1.0)
            signalled = time.monotonic()
            service.send_signal(signal.SIGTERM)
            ready = httpx.get(f"{service.base}/readyz", timeout=10)
            service.wait(timeout=30)
        finally:
            stop.set()
            for t in threads:
                t.join(timeout=30)
    err = service.log
    assert service.returncode == 0, err
    assert ready.status_code == 503 and ready.json()["status"] == "draining"
    # work admitted before the signal was answered after it, not dropped
    assert any(status == 200 and answered > signalled for _, answered, status, _ in answers)
    # before the signal every request was served (a request still in the socket's backlog when the
    # signal came was not admitted yet: it may be refused, below)
    early = [(round(answered - signalled, 3), status, rule) for _, answered, status, rule in answers
             if answered < signalled and status != 200]
    assert not early, early
    refused = [a for a in answers if a[2] != 200]
    assert all((status, rule) == (503, "not_ready") for _, _, status, rule in refused), refused
    # a connection error only once the drain was over and the socket closed
    assert all(float(f.split()[0]) > signalled for f in failures), failures
    assert "SIGTERM: draining" in err and ("drained in" in err) and "Application shutdown complete" in err


def test_a_missing_bundle_stops_start_up_with_the_rule_named(tmp_path):
    missing = tmp_path / "no-bundle"
    proc = subprocess.run([sys.executable, "-m", "service", "--bundle", str(missing), "--port", "0"],
                          env=_env(), cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 3  # uvicorn's start-up failure
    assert f"cannot load the bundle at {missing}" in proc.stderr
    assert "bundle directory does not exist (rule: missing)" in proc.stderr


def test_bad_flags_exit_2_before_loading_anything():
    proc = subprocess.run([sys.executable, "-m", "service", "--port", "99999"], env=_env(), cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "invalid settings" in proc.stderr and "port" in proc.stderr


def test_sighup_swaps_in_the_bundle_deployed_into_the_configured_directory(tiny_bundle, tmp_path):
    import shutil

    import torch

    from tests.firp.bundle_helpers import export_tiny

    deployed = tmp_path / "deployed"
    shutil.copytree(tiny_bundle, deployed)
    torch.manual_seed(7)
    newer = export_tiny(tmp_path / "newer")
    with ServedProcess("service", [*SERVE, "--no-access-log"], _env(FIRP_SERVICE_BUNDLE=str(deployed)),
                       listen_timeout=120) as service:
        base = service.base
        old = httpx.get(f"{base}/v1/model", timeout=10).json()["version"]
        service.send_signal(signal.SIGHUP)  # nothing new deployed yet: the same bundle, read again
        shutil.rmtree(deployed)
        shutil.copytree(newer, deployed)
        service.send_signal(signal.SIGHUP)
        deadline = time.monotonic() + 30
        version = old
        while version == old and time.monotonic() < deadline:
            time.sleep(0.05)
            version = httpx.get(f"{base}/v1/model", timeout=10).json()["version"]
        r = httpx.post(f"{base}/v1/score", json={"image": png_b64(), "plan": plan_list()}, timeout=10)
    err = service.log
    assert version != old, err
    assert r.status_code == 200 and r.json()["model"]["version"] == version
    assert "SIGHUP: reloading the bundle" in err and f"-> {version}" in err
    assert service.returncode == 0, err


def test_json_logs_one_object_per_line_with_the_request_id_and_model_version(tiny_bundle):
    import json

    with ServedProcess("service", [*SERVE, "--log-format", "json"], _env(FIRP_SERVICE_BUNDLE=str(tiny_bundle)),
                       listen_timeout=120) as service:
        r = httpx.post(f"{service.base}/v1/score", json={"image": png_b64(), "plan": plan_list()}, timeout=10,
                       headers={"X-Request-ID": "trial-0-feedc0ffee12"})
    assert r.status_code == 200 and r.headers["X-Request-ID"] == "trial-0-feedc0ffee12"
    objects = [json.loads(line) for line in service.lines if line.strip()]  # every line is one JSON object
    (access,) = [o for o in objects if o.get("request_id") == "trial-0-feedc0ffee12"]
    assert access["route"] == "/v1/score" and access["status"] == 200 and access["plans"] == 1
    assert access["model_version"] == r.json()["model"]["version"] and access["logger"] == "service.access"
    assert any("Uvicorn running on" in o.get("message", "") for o in objects)
