"""``python -m service`` as an operator starts it: a real uvicorn process on loopback.

The service binds port 0 (the OS picks a free one, which nobody else can take between choosing it
and binding it) and the test reads the port from uvicorn's log line.
"""

from __future__ import annotations

import os
import queue
import re
import subprocess
import sys
import threading
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
    # uvicorn shuts down gracefully, then re-raises SIGTERM so the exit status tells how it ended
    assert proc.returncode in (0, -15), err
    assert "ready: bundle tiny" in err and "Application shutdown complete" in err


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
