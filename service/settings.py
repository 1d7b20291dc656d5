"""Service settings: one pydantic-settings class, read from ``FIRP_SERVICE_*`` environment variables.

Why pydantic-settings: a deployment configures the service by environment (container, systemd
unit), a developer by CLI flags (``python -m service --bundle ...``); both land here, so the
limits the service enforces are written down once, typed and validated at start-up instead of
failing at the first request. CLI flags are passed as init arguments, which take precedence over
the environment.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import Field, SecretStr, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from firp.core.bundle_format import shipped_bundle_dir

__all__ = ["DEFAULT_TASK", "ServiceSettings"]

#: The task whose shipped bundle is loaded when neither a bundle nor a task is configured.
DEFAULT_TASK = "stacking"

MIB = 1 << 20


class ServiceSettings(BaseSettings):
    """Everything an operator may set. Limits default to what a planner on the same host needs.

    The image limits bound the work an untrusted request can cause *before* the image is decoded
    (PIL reads the header first): a 100-byte PNG may declare 50,000 x 50,000 pixels.
    """

    model_config = SettingsConfigDict(env_prefix="FIRP_SERVICE_", extra="forbid")

    bundle: Path | None = Field(None, description="bundle directory; default: the shipped bundle of `task`")
    task: str | None = Field(None, description=f"task whose shipped bundle to load (default {DEFAULT_TASK!r}); "
                             "if a bundle is also given, its task must match")
    host: str = "127.0.0.1"
    port: int = Field(8001, ge=0, le=65535)
    threads: int = Field(1, ge=1, le=256, description="torch intra-op threads for inference")
    api_key: SecretStr | None = Field(None, description="if set, /v1 and /v2 model routes need header X-API-Key")
    max_body_bytes: int = Field(16 * MIB, ge=1024, description="larger request bodies get 413")
    max_image_bytes: int = Field(4 * MIB, ge=64, description="larger encoded images get 413")
    min_image_side: int = Field(16, ge=1)
    max_image_side: int = Field(4096, ge=1)
    max_image_pixels: int = Field(4096 * 4096, ge=1)
    max_aspect_ratio: float = Field(4.0, ge=1.0)
    max_batch: int = Field(64, ge=1, le=4096, description="most plans in one /v1/score/batch or V2 call")
    feature_cache_size: int = Field(64, ge=0, description="images whose backbone features are kept (0: off)")
    micro_batch: bool = Field(True, description="score concurrent requests together in one forward pass (requests "
                              "that queued while the previous pass ran; a lone request is never delayed)")
    micro_batch_max_plans: int = Field(64, ge=1, le=4096, description="most plans in one shared forward pass")
    cors_origins: list[str] = Field(default_factory=list, description="CORS allow-list; empty: no CORS")
    log_level: str = "info"
    access_log: bool = True

    @model_validator(mode="after")
    def _image_limits_consistent(self) -> ServiceSettings:
        if self.min_image_side > self.max_image_side:
            raise ValueError(f"min_image_side {self.min_image_side} > max_image_side {self.max_image_side}")
        return self

    @property
    def bundle_dir(self) -> Path:
        """The bundle to load: ``bundle`` if set, else the shipped bundle of ``task``."""
        return self.bundle if self.bundle is not None else shipped_bundle_dir(self.task or DEFAULT_TASK)
