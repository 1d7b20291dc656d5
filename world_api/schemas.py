"""Request and response bodies of a world's HTTP API (pydantic v2).

Requests are strict: a seed of ``5.0``, ``"5"`` or ``true`` is refused rather than coerced, and
unknown fields are refused, so a client's typo fails loudly instead of silently using a default.
The plan itself is only checked for being a list of rows here; its contract (width, length,
one-hot, joint limits) is checked by ``firp.core.contract.validate_plan``, the one validator every
part uses, so its field and rule names are the same everywhere. A world's tasks are known only when
its app is made, so :func:`episode_request_model` builds the request model that names them.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, create_model, field_validator
from pydantic_core import PydanticCustomError

SEED_MAX = 2**63 - 1


class _Request(BaseModel):
    model_config = ConfigDict(strict=True, extra="forbid")


class EpisodeRequestBase(_Request):
    task: str
    seed: int = Field(ge=0, le=SEED_MAX, description="scene seed: the same seed gives the same episode")
    pose_error_mm: float | None = Field(None, ge=0.0, allow_inf_nan=False,
                                        description="override the worker's pose estimate error (std, mm)")
    pose_error_deg: float | None = Field(None, ge=0.0, allow_inf_nan=False,
                                         description="override the worker's yaw estimate error (std, deg)")


def episode_request_model(tasks: tuple[str, ...]) -> type[EpisodeRequestBase]:
    """``EpisodeRequest`` for a world with these tasks: another task is a 422 ``task`` / ``unknown_task``."""
    def known_task(cls, task: str) -> str:
        if task not in tasks:
            raise PydanticCustomError("unknown_task", "unknown task '{task}'; expected one of {tasks}",
                                      {"task": task, "tasks": list(tasks)})
        return task

    return create_model("EpisodeRequest", __base__=EpisodeRequestBase,
                        task=(str, Field(description=f"one of {list(tasks)}")),
                        __validators__={"known_task": field_validator("task")(known_task)})


class ExecuteRequest(_Request):
    plan: list[list[Any]] = Field(description="T x 16 plan of the contract (firp.core.contract)")
    record_frames: bool = Field(False, description="also return the camera image before every step")


class BlockPose(BaseModel):
    position: list[float] = Field(description="x, y, z in metres, world frame")
    yaw: float = Field(description="radians, about world z (modulo the object's symmetry)")


class FinalBlockPose(BaseModel):
    """A pose after execution: null coordinates if the simulation diverged (see ``unstable``)."""

    position: list[float | None]
    yaw: float | None


class Observation(BaseModel):
    """What the planner consumes: pose estimates of the task's objects (``blocks``, by name) and the scene."""

    blocks: dict[str, BlockPose]
    scene: dict[str, Any]


class RobotState(BaseModel):
    joint_names: list[str]
    joint_positions: list[float]


class ImageSize(BaseModel):
    height: int
    width: int


class PoseError(BaseModel):
    mm: float
    deg: float


class EpisodeResponse(BaseModel):
    episode_id: str
    task: str
    seed: int
    image: str = Field(description="initial camera image, base64 PNG (the dataset's frame 0)")
    image_size: ImageSize
    observation: Observation
    robot: RobotState
    pose_error: PoseError
    created_at: datetime
    expires_at: datetime


class ExecuteResponse(BaseModel):
    episode_id: str
    success: bool
    reason: str = Field(description="why, for people: names objects and numbers")
    kind: str = Field(description="the outcome's kind, for programs: 'success' or what failed (the world's "
                                  "names, listed by GET /readyz)")
    final_blocks: dict[str, FinalBlockPose]
    sim_seconds: float
    unstable: bool
    frames: list[str] | None = Field(None, description="base64 PNG before each step, only if requested")


class ErrorDetail(BaseModel):
    field: str | None = Field(description="the offending input, e.g. 'seed' or 'plan[3][2]'; null if none")
    rule: str = Field(description="the rule broken, machine-readable")
    message: str


class ErrorResponse(BaseModel):
    error: ErrorDetail


class Health(BaseModel):
    status: str


class Ready(BaseModel):
    status: str
    world: str
    tasks: list[str]
    outcome_kinds: list[str]
    image_size: int
    pending: int = Field(description="calls (episode starts, executions) waiting for the world's thread or "
                                     "running on it: how busy this worker is")
