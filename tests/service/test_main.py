"""``python -m service`` as an operator starts it: a real uvicorn process on loopback."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

from .helpers import plan_list, png_b64

ROOT = Path(__file__).resolve().parents[2]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("FIRP_SERVICE_")}
    env.update(OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT), **extra)
    return env


def test_starts_from_the_environment_serves_and_stops_cleanly(tiny_bundle):
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "service", "--host", "127.0.0.1", "--port", str(port),
                             "--no-access-log"], env=_env(FIRP_SERVICE_BUNDLE=str(tiny_bundle)), cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        base = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 60
        while True:
            assert proc.poll() is None, proc.communicate()[1]
            try:
                if httpx.get(f"{base}/readyz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, "the service did not become ready within 60 s"
            time.sleep(0.1)
        r = httpx.post(f"{base}/v1/score", json={"image": png_b64(), "plan": plan_list()}, timeout=10)
        assert r.status_code == 200 and r.json()["model"]["name"] == "tiny"
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    # uvicorn shuts down gracefully, then re-raises SIGTERM so the exit status tells how it ended
    assert proc.returncode in (0, -15), err
    assert "ready: bundle tiny" in err and "Application shutdown complete" in err


def test_a_missing_bundle_stops_start_up_with_the_rule_named(tmp_path):
    missing = tmp_path / "no-bundle"
    proc = subprocess.run([sys.executable, "-m", "service", "--bundle", str(missing), "--port", str(_free_port())],
                          env=_env(), cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 3  # uvicorn's start-up failure
    assert f"cannot load the bundle at {missing}" in proc.stderr
    assert "bundle directory does not exist (rule: missing)" in proc.stderr


def test_bad_flags_exit_2_before_loading_anything():
    proc = subprocess.run([sys.executable, "-m", "service", "--port", "99999"], env=_env(), cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "invalid settings" in proc.stderr and "port" in proc.stderr
