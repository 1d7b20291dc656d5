"""What every world worker can be told: where to listen, the camera's size, the perception error, the store.

Each world subclasses :class:`WorldSettings` with its own environment prefix (``FIRP_SIM_*`` for
our world, ``FIRP_ROBOSUITE_*`` for robosuite's); CLI flags override the environment. The image size
and the pose error must match what the scoring model was trained on, so they are settings of the
worker, not of a request -- except the pose error, which a request may override for experiments.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class WorldSettings(BaseSettings):
    model_config = SettingsConfigDict(extra="ignore", frozen=True)

    host: str = Field("127.0.0.1", description="interface to bind")
    port: int = Field(8002, ge=0, le=65535, description="port (0: one the OS picks)")
    image_size: int = Field(84, ge=16, le=512, description="camera image height = width, px")
    pose_error_mm: float = Field(3.0, ge=0.0, allow_inf_nan=False,
                                 description="default std of the object position estimates in the plane")
    pose_error_deg: float = Field(3.0, ge=0.0, allow_inf_nan=False,
                                  description="default std of the object yaw estimates")
    max_episodes: int = Field(1024, ge=1, description="episodes kept at once; the oldest is evicted beyond")
    episode_ttl_seconds: float = Field(3600.0, gt=0.0, allow_inf_nan=False,
                                       description="an episode expires this long after it was created")
    max_queued: int = Field(16, ge=1, le=100_000, description="episode starts and executions waiting or running "
                            "at once; one more gets 503 with Retry-After")
    request_timeout_s: float = Field(0.0, ge=0.0, le=3600.0, description="default time budget of a call (0: none); "
                                     "X-Request-Timeout may set one; a call still queued when it ends gets 504")
    drain_grace_s: float = Field(20.0, ge=0.0, le=3600.0, description="on SIGTERM: readiness 503 at once, queued "
                                 "calls answered for at most this long, then exit 0")
    drain_notice_s: float = Field(1.0, ge=0.0, le=600.0, description="on SIGTERM, readiness answers 503 at least "
                                  "this long before the socket closes")
    log_format: Literal["text", "json"] = Field("text", description="json: one JSON object per log line, one "
                                                "line per request (time, request id, route, status, latency)")
