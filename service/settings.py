"""Service settings: one pydantic-settings class, read from ``FIRP_SERVICE_*`` environment variables.

Why pydantic-settings: a deployment configures the service by environment (container, systemd
unit), a developer by CLI flags (``python -m service --bundle ...``); both land here, so the
limits the service enforces are written down once, typed and validated at start-up instead of
failing at the first request. CLI flags are passed as init arguments, which take precedence over
the environment.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

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
    device: Literal["auto", "cpu", "cuda"] = Field("cpu", description="where the bundle scores: cpu, cuda, or auto "
                                                  "(a CUDA GPU where torch sees one)")
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
    micro_batch_max_plans: int = Field(32, ge=1, le=4096, description="most plans in one shared forward pass "
                                       "(a request of more plans still runs in one pass of its own)")
    max_concurrent_requests: int = Field(64, ge=1, le=100_000, description="scoring requests admitted at once; "
                                         "one more gets 503 with Retry-After (health, readiness, metrics: never)")
    max_queued_plans: int = Field(256, ge=1, le=1_000_000, description="plans waiting for a forward pass at most; a "
                                  "request that would exceed it gets 503 with Retry-After")
    max_queue_wait_s: float = Field(0.1, ge=0.0, le=3600.0, description="a request whose plans would wait longer "
                                    "than this for their pass (from the measured cost of a plan) gets 503 with "
                                    "Retry-After; when the queue is already that long, before its body is read "
                                    "(0: no bound)")
    request_timeout_s: float = Field(30.0, ge=0.0, le=3600.0, description="a scoring request's default time "
                                     "budget (0: none); X-Request-Timeout or V2 parameters.timeout may shorten it; "
                                     "work still queued when it ends is dropped and answered 504")
    drain_grace_s: float = Field(20.0, ge=0.0, le=3600.0, description="on SIGTERM: readiness 503 at once, admitted "
                                 "work is answered for at most this long, then exit 0 (keep it below the "
                                 "orchestrator's grace period: compose's stop_grace_period is 30 s)")
    drain_notice_s: float = Field(1.0, ge=0.0, le=600.0, description="on SIGTERM, readiness answers 503 for at "
                                  "least this long before the socket closes, even when idle, so that a load "
                                  "balancer's probe sees it and stops routing here")
    retry_after_s: int = Field(1, ge=0, le=3600, description="Retry-After (seconds) on a 503 for overload")
    cors_origins: list[str] = Field(default_factory=list, description="CORS allow-list; empty: no CORS")
    log_level: str = "info"
    log_format: Literal["text", "json"] = Field("text", description="json: every log record, and one line per "
                                                "request (time, request id, route, status, latency, model "
                                                "version, plans), as one JSON object per line")
    access_log: bool = Field(True, description="one log line per request")

    @model_validator(mode="after")
    def _image_limits_consistent(self) -> ServiceSettings:
        if self.min_image_side > self.max_image_side:
            raise ValueError(f"min_image_side {self.min_image_side} > max_image_side {self.max_image_side}")
        if self.drain_notice_s > self.drain_grace_s:
            raise ValueError(f"drain_notice_s {self.drain_notice_s} > drain_grace_s {self.drain_grace_s}")
        if self.max_queued_plans < self.max_batch:
            raise ValueError(f"max_queued_plans {self.max_queued_plans} < max_batch {self.max_batch}: a request of "
                             "max_batch plans could never be queued")
        return self

    @property
    def bundle_dir(self) -> Path:
        """The bundle to load: ``bundle`` if set, else the shipped bundle of ``task``."""
        return self.bundle if self.bundle is not None else shipped_bundle_dir(self.task or DEFAULT_TASK)
