"""``python -m service`` as an operator starts it: a real uvicorn process on loopback.

The service binds port 0 (the OS picks a free one, which nobody else can take between choosing it
and binding it) and the test reads the port from uvicorn's log line.
"""

from __future__ import annotations

import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx

from .helpers import plan_list, png_b64

ROOT = Path(__file__).resolve().parents[2]
LISTENING = re.compile(r"Uvicorn running on http://127\.0\.0\.1:(\d+)")


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("FIRP_SERVICE_")}
    env.update(OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT), **extra)
    return env


def _listening_port(proc: subprocess.Popen, lines: list[str], timeout: float = 120.0) -> tuple[int, threading.Thread]:
    """Read the process's stderr (kept in ``lines`` by the returned thread, to the end) until uvicorn
    says where it listens."""
    seen: queue.Queue[str | None] = queue.Queue()

    def pump() -> None:
        for line in proc.stderr:
            lines.append(line)
            seen.put(line)
        seen.put(None)

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    while True:
        line = seen.get(timeout=timeout)
        assert line is not None, "the service exited before listening:\n" + "".join(lines)
        if match := LISTENING.search(line):
            return int(match.group(1)), reader


def test_starts_from_the_environment_serves_and_stops_cleanly(tiny_bundle):
    proc = subprocess.Popen([sys.executable, "-m", "service", "--host", "127.0.0.1", "--port", "0",
                             "--no-access-log"], env=_env(FIRP_SERVICE_BUNDLE=str(tiny_bundle)), cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    reader = None
    try:
        port, reader = _listening_port(proc, lines)
        base = f"http://127.0.0.1:{port}"
        # uvicorn listens only after the lifespan loaded the bundle: ready at once
        assert httpx.get(f"{base}/readyz", timeout=10).status_code == 200
        r = httpx.post(f"{base}/v1/score", json={"image": png_b64(), "plan": plan_list()}, timeout=10)
        assert r.status_code == 200 and r.json()["model"]["name"] == "tiny"
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        if reader is not None:
            reader.join(timeout=30)
    err = "".join(lines)
    # SIGTERM drains (nothing was in flight) and exits 0
    assert proc.returncode == 0, err
    assert "ready: bundle tiny" in err and "drained in" in err and "Application shutdown complete" in err


def test_sigterm_drains_admitted_work_refuses_new_work_and_exits_0(tiny_bundle):
    """Eight clients keep the service busy; SIGTERM arrives. Every request it had admitted is answered
    200; readiness says 503 ``draining`` at once while the socket still accepts; requests after it are
    503 ``not_ready`` with Retry-After, never a reset connection; the process exits 0."""
    proc = subprocess.Popen([sys.executable, "-m", "service", "--host", "127.0.0.1", "--port", "0",
                             "--no-access-log"], env=_env(FIRP_SERVICE_BUNDLE=str(tiny_bundle),
                                                          FIRP_SERVICE_DRAIN_GRACE_S="10",
                                                          # no shedding: this test is about the drain, and a
                                                          # loaded CI machine makes 0.25 s of queue quickly
                                                          FIRP_SERVICE_MAX_QUEUE_WAIT_S="0"),
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    reader = None
    answers: list[tuple[float, float, int, str | None]] = []  # (sent at, answered at, status, rule)
    failures: list[str] = []
    stop = threading.Event()
    try:
        port, reader = _listening_port(proc, lines)
        base = f"http://127.0.0.1:{port}"
        body = {"image": png_b64(), "plans": [plan_list(seed=s) for s in range(4)]}

        def client() -> None:
            with httpx.Client(base_url=base, timeout=30) as http:
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
        for t in threads:
            t.start()
        time.sleep(1.0)
        signalled = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        ready = httpx.get(f"{base}/readyz", timeout=10)
        proc.wait(timeout=30)
        stop.set()
        for t in threads:
            t.join(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
        stop.set()
        if reader is not None:
            reader.join(timeout=30)
    err = "".join(lines)
    assert proc.returncode == 0, err
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
    proc = subprocess.Popen([sys.executable, "-m", "service", "--host", "127.0.0.1", "--port", "0",
                             "--no-access-log"], env=_env(FIRP_SERVICE_BUNDLE=str(deployed)), cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    reader = None
    try:
        port, reader = _listening_port(proc, lines)
        base = f"http://127.0.0.1:{port}"
        old = httpx.get(f"{base}/v1/model", timeout=10).json()["version"]
        proc.send_signal(signal.SIGHUP)  # nothing new deployed yet: the same bundle, read again
        shutil.rmtree(deployed)
        shutil.copytree(newer, deployed)
        proc.send_signal(signal.SIGHUP)
        deadline = time.monotonic() + 30
        version = old
        while version == old and time.monotonic() < deadline:
            time.sleep(0.05)
            version = httpx.get(f"{base}/v1/model", timeout=10).json()["version"]
        r = httpx.post(f"{base}/v1/score", json={"image": png_b64(), "plan": plan_list()}, timeout=10)
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        if reader is not None:
            reader.join(timeout=30)
    err = "".join(lines)
    assert version != old, err
    assert r.status_code == 200 and r.json()["model"]["version"] == version
    assert "SIGHUP: reloading the bundle" in err and f"-> {version}" in err
    assert proc.returncode == 0, err


def test_json_logs_one_object_per_line_with_the_request_id_and_model_version(tiny_bundle):
    import json

    proc = subprocess.Popen([sys.executable, "-m", "service", "--host", "127.0.0.1", "--port", "0",
                             "--log-format", "json"], env=_env(FIRP_SERVICE_BUNDLE=str(tiny_bundle)), cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    reader = None
    try:
        port, reader = _listening_port(proc, lines)
        base = f"http://127.0.0.1:{port}"
        r = httpx.post(f"{base}/v1/score", json={"image": png_b64(), "plan": plan_list()}, timeout=10,
                       headers={"X-Request-ID": "trial-0-feedc0ffee12"})
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        if reader is not None:
            reader.join(timeout=30)
    assert r.status_code == 200 and r.headers["X-Request-ID"] == "trial-0-feedc0ffee12"
    objects = [json.loads(line) for line in lines if line.strip()]  # every line is one JSON object
    (access,) = [o for o in objects if o.get("request_id") == "trial-0-feedc0ffee12"]
    assert access["route"] == "/v1/score" and access["status"] == 200 and access["plans"] == 1
    assert access["model_version"] == r.json()["model"]["version"] and access["logger"] == "service.access"
    assert any("Uvicorn running on" in o.get("message", "") for o in objects)
