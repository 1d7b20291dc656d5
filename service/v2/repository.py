"""The model repository extension's routes (the Open Inference Protocol's, as KServe and Triton serve
it): the index, and load / unload by model name -- the hot swap of :mod:`service.repository`.

* ``POST /v2/repository/index`` -> ``[{"name", "version", "state", "reason"}]``: the model in use
  (``READY``), or the last one unloaded (``UNAVAILABLE``); ``{"ready": true}`` lists only ready ones.
* ``POST /v2/repository/models/{name}/load`` with ``{"parameters": {"bundle": "<dir>"}}`` (a bundle
  directory on the service's filesystem) or no body (the configured bundle, read again): 200 with
  the version now in use, or 422 naming why and keeping the model in use.
* ``POST /v2/repository/models/{name}/unload``: 200; readiness answers 503 until the next load.

Behind the API key when one is set: loading is an operator's action.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fastapi import APIRouter, Request
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ConfigDict, Field, StrictBool, ValidationError

from service.routing import parse_json
from service.errors import ServiceError, error_responses
from service.repository import ModelRepository

__all__ = ["repository_router"]


class RepositoryIndexRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    ready: StrictBool | None = Field(None, description="true: only the models that are ready")


class RepositoryModel(BaseModel):
    name: str
    version: str
    state: str = Field(description="READY, or UNAVAILABLE after an unload")
    reason: str = ""


class RepositoryLoadRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    parameters: dict[str, Any] | None = Field(None, description="bundle: a bundle directory to load (default: the "
                                              "configured one, read again)")


def _repository(request: Request) -> ModelRepository:
    return request.app.state.repository


async def _body(request: Request, model: type[BaseModel]) -> Any:
    """The optional JSON body, parsed here: Triton's client sends it without a Content-Type, and FastAPI
    would read such a body as bytes."""
    raw = await request.body()
    if not raw.strip():
        return None
    try:
        data = parse_json(raw)
    except ValueError as exc:
        raise ServiceError(422, "body", "json_invalid", f"the body is not JSON: {exc}") from exc
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise RequestValidationError(exc.errors()) from exc


def _optional_body(model: type[BaseModel]) -> dict[str, Any]:
    """The OpenAPI description of a body the route parses itself (:func:`_body`)."""
    return {"requestBody": {"required": False, "content": {"application/json": {"schema": model.model_json_schema()}}}}


def repository_router(guarded: list[Any]) -> APIRouter:
    router = APIRouter(prefix="/v2/repository", tags=["open inference protocol: model repository"],
                       dependencies=guarded)
    errors = error_responses(401, 404, 422, v2=True)

    @router.post("/index", response_model=list[RepositoryModel], responses=errors, summary="Models in the repository",
                 openapi_extra=_optional_body(RepositoryIndexRequest))
    async def index(request: Request) -> list[RepositoryModel]:
        body = await _body(request, RepositoryIndexRequest)
        repo = _repository(request)
        model = repo.model
        if model is not None:
            return [RepositoryModel(name=model.name, version=model.version, state="READY")]
        if repo.unloaded is None or (body is not None and body.ready):
            return []
        name, version = repo.unloaded
        return [RepositoryModel(name=name, version=version, state="UNAVAILABLE", reason="unloaded")]

    @router.post("/models/{name}/load", response_model=RepositoryModel, responses=errors,
                 summary="Load (or swap in) a bundle; the model in use serves until the new one is warm",
                 openapi_extra=_optional_body(RepositoryLoadRequest))
    async def load(name: str, request: Request) -> RepositoryModel:
        body = await _body(request, RepositoryLoadRequest)
        parameters = (body.parameters if body is not None else None) or {}
        unknown = sorted(set(parameters) - {"bundle"})
        if unknown:
            raise ServiceError(422, f"parameters.{unknown[0]}", "unknown_parameter",
                               f"load takes parameters.bundle only, got {unknown[0]!r}")
        bundle = parameters.get("bundle")
        if bundle is not None and (not isinstance(bundle, str) or not bundle):
            raise ServiceError(422, "parameters.bundle", "type", f"a bundle directory (string), got {bundle!r}")
        path = Path(bundle) if bundle is not None else request.app.state.settings.bundle_dir
        model = await _repository(request).load(path, expected_name=name)
        return RepositoryModel(name=model.name, version=model.version, state="READY")

    @router.post("/models/{name}/unload", response_model=RepositoryModel, responses=errors,
                 summary="Unload the model: readiness 503 until the next load")
    async def unload(name: str, request: Request) -> RepositoryModel:
        repo = _repository(request)
        model = repo.model
        await repo.unload(name)
        assert model is not None
        return RepositoryModel(name=model.name, version=model.version, state="UNAVAILABLE", reason="unloaded")

    return router
