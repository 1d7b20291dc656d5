"""A world's HTTP API: start seeded episodes, execute plans on them, report the outcome.

``POST /v1/episodes`` fixes an episode (task, seed, pose error) and returns what a planner and a
scorer see of it: the pose estimates and the initial camera image (bit-identical to a dataset's
frame 0). ``POST /v1/episodes/{id}/execute`` runs a plan from that episode's initial state --
always from the initial state, so executing the same plan again gives the same outcome. The world is
built in the background after start-up; ``/readyz`` turns 200 when it is built and has rendered
once, while ``/healthz`` only says the process answers.
"""

# No ``from __future__ import annotations``: the episode request model is made per app (it names the
# world's tasks), and FastAPI must see the route's annotation as that class, not as a string.
import asyncio
import logging
import time
from contextlib import asynccontextmanager
from datetime import datetime, timezone
from typing import TYPE_CHECKING, AsyncIterator, Callable

from fastapi import FastAPI, Request, Response

from firp.core import http_errors
from firp.core.contract import JOINT_NAMES, validate_plan
from firp.core.deadlines import TIMEOUT_HEADER, parse_timeout
from firp.core.http_errors import ApiError, error_response
from firp.core.request_log import RequestLog
from firp.core.tracing import configure_tracing, instrument_app, tracer_of
from world_api.backend import WorldBackend
from world_api.runner import WorldRunner
from world_api.schemas import (
    EpisodeResponse, ErrorResponse, ExecuteRequest, ExecuteResponse, Health, Ready, episode_request_model,
)
from world_api.settings import WorldSettings
from world_api.store import EpisodeStore, StoredEpisode

if TYPE_CHECKING:
    from opentelemetry.sdk.trace import TracerProvider
    from opentelemetry.trace import Tracer

ERRORS = {code: {"model": ErrorResponse} for code in (400, 404, 422, 500, 503, 504)}


def _timestamp(seconds: float) -> datetime:
    return datetime.fromtimestamp(seconds, tz=timezone.utc)


def episode_response(episode: StoredEpisode, image_size: int) -> dict:
    start = episode.start
    return {
        "episode_id": episode.episode_id, "task": start.task, "seed": start.seed, "image": episode.image_b64,
        "image_size": {"height": image_size, "width": image_size}, "observation": start.observation,
        "robot": {"joint_names": list(JOINT_NAMES), "joint_positions": start.joint_positions.tolist()},
        "pose_error": {"mm": episode.pose_error[0], "deg": episode.pose_error[1]},
        "created_at": _timestamp(episode.created_at), "expires_at": _timestamp(episode.expires_at),
    }


class _State:
    """What the lifespan builds: the runner, the episode store and the warm-up's progress."""

    def __init__(self, backend: WorldBackend, settings: WorldSettings, clock: Callable[[], float],
                 log: logging.Logger, tracer: "Tracer | None" = None):
        self.settings = settings
        self.runner = WorldRunner(backend, settings.max_queued, tracer=tracer)
        self.draining = False  # SIGTERM (firp.core.draining): readiness 503, no new work
        self.store = EpisodeStore(settings.max_episodes, settings.episode_ttl_seconds, clock)
        self.ready = False
        self.warm_up_error: str | None = None
        self.log = log

    async def warm_up(self) -> None:
        backend = self.runner.backend
        try:
            await self.runner.warm_up()
            self.ready = True
            self.log.info("%s ready: tasks %s at %d px", backend.name, ", ".join(backend.tasks), backend.image_size)
        except Exception as exc:  # reported by /readyz: the process stays up so the cause can be read
            self.warm_up_error = f"{type(exc).__name__}: {exc}"
            self.log.exception("warm-up failed")


def create_world_app(backend: WorldBackend, settings: WorldSettings, clock: Callable[[], float] = time.time,
                     title: str = "firp world", tracer_provider: "TracerProvider | None" = None) -> FastAPI:
    """The API over ``backend`` (built lazily: its worlds are made on the runner's thread at warm-up);
    ``clock`` (seconds since the epoch) is injectable so tests can expire episodes. Tracing
    (:mod:`firp.core.tracing`) is on when ``tracer_provider`` is given or the ``OTEL_*`` variables ask."""
    log = logging.getLogger(backend.name)
    if tracer_provider is None:
        tracer_provider = configure_tracing(f"firp-{backend.name.replace('_', '-')}")
    EpisodeRequest = episode_request_model(tuple(backend.tasks))

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        state = _State(backend, settings, clock, log, tracer_of(tracer_provider, f"firp.{backend.name}"))
        app.state.sim = state
        warm_up = asyncio.create_task(state.warm_up())
        try:
            yield
        finally:
            await warm_up
            await state.runner.close()

    app = FastAPI(title=title, version="1", lifespan=lifespan, description=__doc__.split("\n\n")[0])
    http_errors.install_error_handlers(app, log)
    app.add_middleware(RequestLog, logger=f"{backend.name}.access")  # the request id, one log line per request
    if tracer_provider is not None:  # outermost: the server span covers the request's whole life
        instrument_app(app, tracer_provider)

    def state_of(request: Request) -> _State:
        return request.app.state.sim

    def admit(request: Request) -> float | None:
        """The call's deadline (``X-Request-Timeout``, else the default budget), or 503 while draining."""
        if state_of(request).draining:
            raise ApiError(503, None, "not_ready", "the worker is draining (stopping); start the episode on "
                           "another worker", headers={"Retry-After": "1"})
        header = request.headers.get(TIMEOUT_HEADER)
        budget = parse_timeout(header) if header is not None else (settings.request_timeout_s or None)
        return None if budget is None else time.monotonic() + budget

    @app.get("/healthz", response_model=Health)
    async def healthz() -> dict:
        return {"status": "ok"}

    @app.get("/readyz", response_model=Ready, responses={503: {"model": ErrorResponse}})
    async def readyz(request: Request):
        state = state_of(request)
        if state.draining:
            return error_response(request.scope, 503, None, "draining", "stopping: admitted work is being finished")
        if not state.ready:
            message = (f"warm-up failed: {state.warm_up_error}" if state.warm_up_error
                       else "building the worlds and rendering once")
            return error_response(request.scope, 503, None, "not_ready", message)
        return {"status": "ready", "world": backend.name, "tasks": list(backend.tasks),
                "outcome_kinds": list(backend.outcome_kinds), "image_size": backend.image_size,
                "pending": state.runner.pending}

    @app.post("/v1/episodes", response_model=EpisodeResponse, status_code=201, responses=ERRORS)
    async def create_episode(body: EpisodeRequest, request: Request) -> dict:  # type: ignore[valid-type]
        state = state_of(request)
        deadline = admit(request)
        mm = settings.pose_error_mm if body.pose_error_mm is None else body.pose_error_mm
        deg = settings.pose_error_deg if body.pose_error_deg is None else body.pose_error_deg
        start, image_b64 = await state.runner.begin(body.task, body.seed, float(mm), float(deg), deadline)
        episode = state.store.add(start, (float(mm), float(deg)), image_b64)
        return episode_response(episode, backend.image_size)

    def stored(state: _State, episode_id: str) -> StoredEpisode:
        episode = state.store.get(episode_id)
        if episode is None:
            raise ApiError(404, "episode_id", "unknown_episode",
                           f"no episode {episode_id!r}: never created, deleted, or expired (episodes live "
                           f"{settings.episode_ttl_seconds:g} s, at most {settings.max_episodes} are kept); "
                           f"start it again with the same task and seed to get the same episode")
        return episode

    @app.post("/v1/episodes/{episode_id}/execute", response_model=ExecuteResponse,
              response_model_exclude_none=True, responses=ERRORS)
    async def execute(episode_id: str, body: ExecuteRequest, request: Request) -> dict:
        state = state_of(request)
        deadline = admit(request)
        episode = stored(state, episode_id)
        plan = validate_plan(body.plan)  # PlanValidationError -> 422 with the contract's field and rule
        run = await state.runner.execute(episode.start, plan, body.record_frames, deadline)
        o = run.outcome
        return {"episode_id": episode_id, "success": bool(o.success), "reason": o.reason, "kind": o.kind,
                "final_blocks": o.final_blocks, "sim_seconds": o.sim_seconds, "unstable": bool(o.unstable),
                "frames": run.frames_b64}

    @app.delete("/v1/episodes/{episode_id}", status_code=204, responses=ERRORS)
    async def delete_episode(episode_id: str, request: Request) -> Response:
        stored(state_of(request), episode_id)
        state_of(request).store.delete(episode_id)
        return Response(status_code=204)

    return app
