"""Hot swap of the ensemble: load, verify and warm a bundle off the serving path, then switch at once.

Why in the service and not by restarting it: a restart costs the bundle's load and warm-up (seconds)
during which a replica serves nothing, and requests in flight are lost unless drained. A swap serves
the old bundle until the new one is verified (:func:`firp.bundle.load_bundle`: manifest, sha256 of
every weights file, shapes) and has scored a warm-up pass; then one assignment makes it the model
every new pass uses (:class:`~service.batching.MicroBatcher` reads its model once per pass, so a
pass is never split between two bundles). If anything fails, the old bundle stays and the error
names the file and the rule. Responses name the version that scored them
(:class:`~service.scorer.ModelScores`), so a client can tell on which side of a swap it was served.

Driven by the Open Inference Protocol's model repository extension (``POST /v2/repository/index``,
``.../models/{name}/load`` with ``{"parameters": {"bundle": "<dir>"}}`` or the configured bundle,
``.../unload``; :mod:`service.v2.repository`) and by SIGHUP (the configured bundle's directory, read
again: deploy a new bundle into it, then ``kill -HUP``).
"""

from __future__ import annotations

import logging
from pathlib import Path

import anyio
import anyio.to_thread
from fastapi import FastAPI

from firp.bundle import BundleError
from service.errors import ServiceError
from service.scorer import ServiceModel

__all__ = ["ModelRepository"]

log = logging.getLogger("service")


class ModelRepository:
    """The one model slot of a service app: what is loaded, from where, and the swap."""

    def __init__(self, app: FastAPI):
        self.app = app
        self.lock = anyio.Lock()  # one load or unload at a time
        self.path: Path | None = None  # where the model in use was loaded from
        self.last_error: str | None = None
        self.unloaded: tuple[str, str] | None = None  # (name, version) of the model last unloaded

    @property
    def model(self) -> ServiceModel | None:
        return self.app.state.model

    def install(self, model: ServiceModel, path: Path) -> None:
        """Make ``model`` the one every new pass uses (the event loop's single assignment is the switch)."""
        state, metrics = self.app.state, self.app.state.metrics
        old = state.model
        state.model = model
        if state.batcher is not None:
            state.batcher.model = model
        self.path = path
        self.unloaded = None
        if old is not None and old is not model:
            metrics.model_info.labels(old.name, old.version, old.task).set(0)
        metrics.model_info.labels(model.name, model.version, model.task).set(1)
        metrics.model_informative.set({True: 1, False: 0, None: -1}[model.informative])
        if state.phase in ("ready", "unloaded"):
            state.phase = "ready"
            metrics.ready.set(1)

    async def load(self, path: Path, expected_name: str | None = None) -> ServiceModel:
        """Load, verify and warm the bundle at ``path`` in a worker thread, then install it. On any
        failure the model in use stays and the error says why (422, field ``parameters.bundle``)."""
        settings = self.app.state.settings
        async with self.lock:
            try:
                model = await anyio.to_thread.run_sync(ServiceModel.load, path, settings.feature_cache_size,
                                                     settings.device)
            except BundleError as exc:
                self.last_error = f"{path}: {exc}"
                raise ServiceError(422, "parameters.bundle", exc.rule,
                                   f"cannot load the bundle at {path}: {exc}; the model in use is unchanged") from exc
            current = self.model
            task = current.task if current is not None else settings.task
            if task is not None and model.task != task:
                self.last_error = f"{path}: task {model.task!r}"
                raise ServiceError(422, "parameters.bundle", "task_mismatch", f"the bundle at {path} is for task "
                                   f"{model.task!r}; this service scores {task!r}; the model in use is unchanged")
            if expected_name is not None and model.name != expected_name:
                self.last_error = f"{path}: name {model.name!r}"
                raise ServiceError(422, "name", "name_mismatch", f"the bundle at {path} is model {model.name!r}, not "
                                   f"{expected_name!r}; the model in use is unchanged")
            try:
                warmup_ms = await anyio.to_thread.run_sync(model.warm_up)
            except Exception as exc:  # noqa: BLE001 - a bundle that cannot score must not be installed
                self.last_error = f"{path}: warm-up failed: {exc}"
                raise ServiceError(422, "parameters.bundle", "warm_up", f"the bundle at {path} failed its warm-up "
                                   f"pass ({exc}); the model in use is unchanged") from exc
            old = self.model
            self.install(model, path)
            self.last_error = None
            log.info("swapped: bundle %s version %s -> %s (from %s), warm-up %.0f ms",
                     model.name, old.version if old is not None else "none", model.version, path, warmup_ms)
            return model

    async def unload(self, name: str) -> None:
        """No model: readiness 503 ``unloaded``, scoring 503 ``not_ready``, until a load."""
        async with self.lock:
            model = self.model
            if model is None:
                raise ServiceError(404, "name", "unknown_model", f"no model is loaded (asked to unload {name!r})")
            if model.name != name:
                raise ServiceError(404, "name", "unknown_model", f"this service serves model {model.name!r}, not {name!r}")
            state = self.app.state
            state.model = None
            self.unloaded = (model.name, model.version)
            if state.phase == "ready":
                state.phase = "unloaded"
            state.metrics.ready.set(0)
            state.metrics.model_info.labels(model.name, model.version, model.task).set(0)
            log.info("unloaded: bundle %s version %s", model.name, model.version)

    async def reload(self) -> None:
        """SIGHUP: the configured bundle's directory, read again; a failure is logged, the old model stays."""
        path = self.app.state.settings.bundle_dir
        try:
            await self.load(path)
        except ServiceError as exc:
            log.error("SIGHUP: %s", exc.message)
