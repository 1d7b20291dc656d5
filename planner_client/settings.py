"""Settings of the planner client, from ``FIRP_PLANNER_*`` environment variables; CLI flags override them.

The same scheme as the scoring service's (``FIRP_SERVICE_*``) and the sim worker's (``FIRP_SIM_*``):
a deployment (compose, a job scheduler) sets where the two services are, a person passes flags.
"""

from __future__ import annotations

from pydantic import Field, SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict

__all__ = ["PlannerSettings"]


class PlannerSettings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="FIRP_PLANNER_", extra="ignore", frozen=True)

    sim_url: str | None = Field(None, description="a running sim worker; unset: the run launches one on loopback")
    service_url: str | None = Field(None, description="a running scoring service; unset: the run launches one")
    api_key: SecretStr | None = Field(None, description="X-API-Key sent to the scoring service")
    ready_timeout: int = Field(120, ge=1, le=3600, description="seconds to wait for the services to be ready")
