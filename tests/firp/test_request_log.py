"""Request ids and request log lines (firp.core.request_log), on a bare FastAPI app: echoed or
generated ids, malformed ids refused, one JSON object per request with the route's own fields."""

from __future__ import annotations

import json
import logging

import pytest
from fastapi import FastAPI, Request
from fastapi.testclient import TestClient

from firp.core import http_errors
from firp.core.request_log import SCOPE_LOG, JsonFormatter, RequestLog


def _app() -> FastAPI:
    app = FastAPI()
    http_errors.install_error_handlers(app, logging.getLogger("test"))

    @app.post("/items/{item}")
    async def item(item: str, request: Request) -> dict:
        request.scope[SCOPE_LOG]["plans"] = 3
        return {"item": item}

    app.add_middleware(RequestLog, logger="test.access")
    return app


@pytest.fixture()
def client():
    with TestClient(_app()) as c:
        yield c


def test_a_given_id_is_echoed_and_logged_with_the_route_template(client, caplog):
    with caplog.at_level(logging.INFO, logger="test.access"):
        r = client.post("/items/7", headers={"X-Request-ID": "trial-3-abc.DEF:1/2"})
    assert r.status_code == 200 and r.headers["X-Request-ID"] == "trial-3-abc.DEF:1/2"
    (record,) = [rec for rec in caplog.records if rec.name == "test.access"]
    fields = record.fields
    assert {k: fields[k] for k in ("request_id", "method", "route", "status", "plans")} == {
        "request_id": "trial-3-abc.DEF:1/2", "method": "POST", "route": "/items/{item}", "status": 200, "plans": 3}
    assert fields["latency_ms"] >= 0
    line = json.loads(JsonFormatter().format(record))  # one JSON object per line
    assert line["request_id"] == "trial-3-abc.DEF:1/2" and line["level"] == "info" and line["time"].endswith("Z")


def test_an_id_is_generated_when_none_is_given_and_errors_carry_it_too(client):
    a, b = client.post("/items/1"), client.get("/nowhere")
    assert len(a.headers["X-Request-ID"]) == 32 and a.headers["X-Request-ID"] != b.headers["X-Request-ID"]
    assert b.status_code == 404 and len(b.headers["X-Request-ID"]) == 32


@pytest.mark.parametrize("bad", ["x" * 129, "has space", "semi;colon", ""])
def test_a_malformed_id_is_refused_naming_the_header_and_never_echoed(client, bad):
    r = client.post("/items/1", headers={"X-Request-ID": bad})
    assert r.status_code == 400
    assert (r.json()["error"]["field"], r.json()["error"]["rule"]) == ("X-Request-ID", "request_id")
    assert r.headers["X-Request-ID"] != bad and len(r.headers["X-Request-ID"]) == 32


def test_plain_records_become_json_with_their_message():
    record = logging.LogRecord("service", logging.WARNING, __file__, 1, "drained %d", (3,), None)
    assert json.loads(JsonFormatter().format(record))["message"] == "drained 3"
