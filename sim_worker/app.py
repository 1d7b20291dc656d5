"""The sim worker's HTTP API: start seeded episodes, execute plans on them, report the outcome.

``POST /v1/episodes`` fixes an episode (task, seed, pose error) and returns what a planner and a
scorer see of it: the pose estimates and the initial camera image (bit-identical to a dataset's
frame 0). ``POST /v1/episodes/{id}/execute`` runs a plan from that episode's initial state --
always from the initial state, so executing the same plan again gives the same outcome. Worlds are
built in the background after start-up; ``/readyz`` turns 200 when they are built and have
rendered once, while ``/healthz`` only says the process answers.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from contextlib import asynccontextmanager
from datetime import datetime, timezone
from typing import AsyncIterator, Callable

import numpy as np
from fastapi import FastAPI, Request, Response

from firp.core.contract import JOINT_NAMES, validate_plan
from sim_worker.errors import ApiError, error_response, install_error_handlers
from sim_worker.perception import PoseErrorConfig
from sim_worker.runner import SimRunner
from sim_worker.scene import BLOCK_NAMES
from sim_worker.schemas import (
    EpisodeRequest, EpisodeResponse, ErrorResponse, ExecuteRequest, ExecuteResponse, Health, Ready,
)
from sim_worker.settings import SimWorkerSettings
from sim_worker.store import EpisodeStore, StoredEpisode
from sim_worker.tasks import TASK_NAMES

log = logging.getLogger("sim_worker")

ERRORS = {code: {"model": ErrorResponse} for code in (404, 422, 500, 503)}


def _timestamp(seconds: float) -> datetime:
    return datetime.fromtimestamp(seconds, tz=timezone.utc)


def _finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def block_poses_json(poses: np.ndarray) -> dict:
    """Block poses by name; a coordinate the physics lost (non-finite after a divergence) is null,
    since JSON has no NaN."""
    return {name: {"position": [_finite_or_none(v) for v in poses[i, :3]], "yaw": _finite_or_none(poses[i, 3])}
            for i, name in enumerate(BLOCK_NAMES)}


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

    def __init__(self, settings: SimWorkerSettings, clock: Callable[[], float]):
        self.settings = settings
        self.runner = SimRunner(settings.image_size)
        self.store = EpisodeStore(settings.max_episodes, settings.episode_ttl_seconds, clock)
        self.ready = False
        self.warm_up_error: str | None = None

    async def warm_up(self) -> None:
        try:
            await self.runner.warm_up()
            self.ready = True
            log.info("sim worker ready: worlds for %s built at %d px", ", ".join(TASK_NAMES),
                     self.settings.image_size)
        except Exception as exc:  # reported by /readyz: the process stays up so the cause can be read
            self.warm_up_error = f"{type(exc).__name__}: {exc}"
            log.exception("warm-up failed")


def create_app(settings: SimWorkerSettings | None = None, clock: Callable[[], float] = time.time) -> FastAPI:
    """The app; ``clock`` (seconds since the epoch) is injectable so tests can expire episodes."""
    settings = settings or SimWorkerSettings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        state = _State(settings, clock)
        app.state.sim = state
        warm_up = asyncio.create_task(state.warm_up())
        try:
            yield
        finally:
            await warm_up
            await state.runner.close()

    app = FastAPI(title="firp sim worker", version="1", lifespan=lifespan,
                  description=__doc__.split("\n\n")[0] if __doc__ else None)
    install_error_handlers(app)

    def state_of(request: Request) -> _State:
        return request.app.state.sim

    @app.get("/healthz", response_model=Health)
    async def healthz() -> dict:
        return {"status": "ok"}

    @app.get("/readyz", response_model=Ready, responses={503: {"model": ErrorResponse}})
    async def readyz(request: Request):
        state = state_of(request)
        if not state.ready:
            message = (f"warm-up failed: {state.warm_up_error}" if state.warm_up_error
                       else "building the worlds and rendering once")
            return error_response(request.scope, 503, None, "not_ready", message)
        return {"status": "ready", "tasks": list(TASK_NAMES), "image_size": settings.image_size}

    @app.post("/v1/episodes", response_model=EpisodeResponse, status_code=201, responses=ERRORS)
    async def create_episode(body: EpisodeRequest, request: Request) -> dict:
        state = state_of(request)
        mm = settings.pose_error_mm if body.pose_error_mm is None else body.pose_error_mm
        deg = settings.pose_error_deg if body.pose_error_deg is None else body.pose_error_deg
        start, image_b64 = await state.runner.begin(body.task, body.seed, PoseErrorConfig.from_mm_deg(mm, deg))
        episode = state.store.add(start, (float(mm), float(deg)), image_b64)
        return episode_response(episode, settings.image_size)

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
        episode = stored(state, episode_id)
        plan = validate_plan(body.plan)  # PlanValidationError -> 422 with the contract's field and rule
        run = await state.runner.execute(episode.start, plan, body.record_frames)
        r = run.result
        return {"episode_id": episode_id, "success": bool(r.success), "reason": r.reason, "kind": r.kind,
                "final_blocks": block_poses_json(r.final_block_poses), "sim_seconds": r.sim_seconds,
                "unstable": bool(r.unstable), "frames": run.frames_b64}

    @app.delete("/v1/episodes/{episode_id}", status_code=204, responses=ERRORS)
    async def delete_episode(episode_id: str, request: Request) -> Response:
        stored(state_of(request), episode_id)
        state_of(request).store.delete(episode_id)
        return Response(status_code=204)

    return app
