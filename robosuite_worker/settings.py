"""Settings of the robosuite worker, from ``FIRP_ROBOSUITE_*`` environment variables or CLI flags."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, field_validator
from pydantic_settings import NoDecode, SettingsConfigDict

from world_api.settings import WorldSettings

__all__ = ["RobosuiteSettings"]


class RobosuiteSettings(WorldSettings):
    model_config = SettingsConfigDict(env_prefix="FIRP_ROBOSUITE_", extra="ignore", frozen=True)

    port: int = Field(8003, ge=0, le=65535, description="port (0: one the OS picks); the sim worker's is 8002")
    camera: str = Field("agentview", description="the robosuite camera of the initial image and the frames, for "
                                                 "every task served (each must have it)")
    tasks: Annotated[tuple[str, ...], NoDecode] = Field(
        (), description="the tasks served, comma-separated (default: every robosuite task); e.g. stack_three alone "
                        "with camera workspaceview, which the other tasks lack")

    @field_validator("tasks", mode="before")
    @classmethod
    def _task_names(cls, value: object) -> tuple[str, ...]:
        from robosuite_worker.tasks import TASKS

        names = tuple(n.strip() for n in value.split(",") if n.strip()) if isinstance(value, str) else tuple(value)
        unknown = [n for n in names if n not in TASKS]
        if unknown:
            raise ValueError(f"unknown task(s) {', '.join(map(repr, unknown))}; expected some of {', '.join(TASKS)}")
        return names
