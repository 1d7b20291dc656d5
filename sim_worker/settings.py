"""Settings of the sim worker, from ``FIRP_SIM_*`` environment variables or CLI flags (see :mod:`world_api.settings`)."""

from __future__ import annotations

from pydantic_settings import SettingsConfigDict

from world_api.settings import WorldSettings

__all__ = ["SimWorkerSettings"]


class SimWorkerSettings(WorldSettings):
    model_config = SettingsConfigDict(env_prefix="FIRP_SIM_", extra="ignore", frozen=True)
