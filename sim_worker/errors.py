"""The sim worker's errors: the one shape of :mod:`firp.core.http_errors`, shared with the scoring
service, so a planner reads errors from both the same way:

    {"error": {"field": "episode_id", "rule": "unknown_episode", "message": "..."}}
"""

from __future__ import annotations

import logging

from fastapi import FastAPI

from firp.core import http_errors
from firp.core.http_errors import ApiError, error_response

__all__ = ["ApiError", "error_response", "install_error_handlers"]

log = logging.getLogger("sim_worker")


def install_error_handlers(app: FastAPI) -> None:
    http_errors.install_error_handlers(app, log)
