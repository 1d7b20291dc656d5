"""The containers' readiness probe (python -m firp.core.probe): 0 only on a 200 answer."""

from __future__ import annotations

import http.server
import subprocess
import sys
import threading

import pytest

from firp.core.probe import main, probe_url


class _Readyz(http.server.BaseHTTPRequestHandler):
    status = 200

    def do_GET(self):  # noqa: N802 (the standard library's name)
        self.send_response(type(self).status)
        self.end_headers()
        self.wfile.write(b"{}")

    def log_message(self, *args):
        pass


@pytest.fixture
def server():
    handler = type("Handler", (_Readyz,), {"status": 200})
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield httpd, handler
    httpd.shutdown()
    httpd.server_close()


def test_ready_only_on_200(server, capsys):
    httpd, handler = server
    url = f"http://127.0.0.1:{httpd.server_port}/readyz"
    assert main([url]) == 0
    handler.status = 503
    assert main([url]) == 1
    assert capsys.readouterr().err.strip().endswith(": 503")


def test_nothing_listening_is_not_ready(server, capsys):
    httpd, _ = server
    port = httpd.server_port
    httpd.shutdown()
    httpd.server_close()
    assert main([f"http://127.0.0.1:{port}/readyz", "--timeout", "1"]) == 1
    assert "refused" in capsys.readouterr().err.lower()


def test_the_port_comes_from_the_environment_when_set(server, monkeypatch):
    httpd, _ = server
    monkeypatch.setenv("FIRP_SERVICE_PORT", str(httpd.server_port))
    assert probe_url("http://127.0.0.1:8001/readyz", "FIRP_SERVICE_PORT") == f"http://127.0.0.1:{httpd.server_port}/readyz"
    assert main(["http://127.0.0.1:1/readyz", "--port-env", "FIRP_SERVICE_PORT"]) == 0
    monkeypatch.delenv("FIRP_SERVICE_PORT")
    assert probe_url("http://127.0.0.1:8001/readyz", "FIRP_SERVICE_PORT") == "http://127.0.0.1:8001/readyz"
    monkeypatch.setenv("FIRP_SERVICE_PORT", "80x")
    with pytest.raises(SystemExit) as exit_:
        main(["http://127.0.0.1:8001/readyz", "--port-env", "FIRP_SERVICE_PORT"])
    assert exit_.value.code == 2


def test_runs_as_a_module_as_the_health_checks_call_it(server):
    httpd, _ = server
    done = subprocess.run([sys.executable, "-m", "firp.core.probe", f"http://127.0.0.1:{httpd.server_port}/readyz"],
                          capture_output=True, text=True, timeout=30)
    assert done.returncode == 0 and done.stdout.strip().endswith(": 200")
