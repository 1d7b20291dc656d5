"""Settings of the robosuite worker, from ``FIRP_ROBOSUITE_*`` environment variables or CLI flags."""

from __future__ import annotations

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from world_api.settings import WorldSettings

__all__ = ["RobosuiteSettings"]


class RobosuiteSettings(WorldSettings):
    model_config = SettingsConfigDict(env_prefix="FIRP_ROBOSUITE_", extra="ignore", frozen=True)

    port: int = Field(8003, ge=0, le=65535, description="port (0: one the OS picks); the sim worker's is 8002")
    camera: str = Field("agentview", description="the robosuite camera of the initial image and the frames")
