"""The one error shape both HTTP APIs share (firp.core.http_errors), on a bare FastAPI app."""

import logging

import httpx
import pytest
from fastapi import FastAPI
from pydantic import BaseModel

from firp.core.contract import PlanValidationError
from firp.core.http_errors import SCOPE_RULE, ApiError, field_from_loc, install_error_handlers


@pytest.mark.parametrize("loc, field", [
    (("body", "plan", 3, 7), "plan[3][7]"),
    (("body",), "body"),
    (("query", "seed"), "seed"),
    (("body", "plans", 0, "task"), "plans[0].task"),
])
def test_field_from_loc(loc, field):
    assert field_from_loc(loc) == field


class Body(BaseModel):
    seed: int


def _app(seen_rules: list) -> FastAPI:
    app = FastAPI()
    install_error_handlers(app, logging.getLogger("test-api"))

    @app.middleware("http")
    async def record_rule(request, call_next):
        response = await call_next(request)
        seen_rules.append(request.scope.get(SCOPE_RULE))
        return response

    @app.post("/refuse")
    async def refuse():
        raise ApiError(409, "episode_id", "busy", "try again", headers={"Retry-After": "1"})

    @app.post("/plan")
    async def plan():
        raise PlanValidationError("plan[2][0]", "one_hot", "row 2 is not one-hot")

    @app.post("/body")
    async def body(b: Body):
        return {"seed": b.seed}

    @app.post("/crash")
    async def crash():
        raise RuntimeError("secret internals")

    return app


@pytest.mark.anyio
async def test_every_error_has_the_one_shape(caplog):
    rules: list = []
    transport = httpx.ASGITransport(app=_app(rules), raise_app_exceptions=False)
    async with httpx.AsyncClient(transport=transport, base_url="http://t") as client:
        r = await client.post("/refuse")
        assert r.status_code == 409 and r.headers["Retry-After"] == "1"
        assert r.json() == {"error": {"field": "episode_id", "rule": "busy", "message": "try again"}}
        r = await client.post("/plan")
        assert r.status_code == 422 and r.json()["error"] == {"field": "plan[2][0]", "rule": "one_hot",
                                                               "message": "row 2 is not one-hot"}
        r = await client.post("/body", json={"seed": "x"})
        assert r.status_code == 422 and r.json()["error"]["field"] == "seed"
        assert r.json()["error"]["rule"] == "int_parsing"
        r = await client.get("/nowhere")
        assert r.status_code == 404 and r.json()["error"]["rule"] == "not_found"
        assert rules == ["busy", "one_hot", "int_parsing", "not_found"]  # each response left its rule for metrics
        with caplog.at_level(logging.ERROR, logger="test-api"):
            r = await client.post("/crash")
        assert r.status_code == 500 and r.json()["error"]["rule"] == "internal"
        assert "secret" not in r.text  # the client learns nothing about the internals ...
        assert "secret internals" in caplog.text  # ... the log has the traceback
