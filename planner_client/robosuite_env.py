"""Where the robosuite world's Python is: robosuite runs in its own environment beside ours.

robosuite 1.5.2 needs MuJoCo 3.3 and ``numpy<2``; our world is pinned to MuJoCo 4. ``make
robosuite-install`` makes ``.venv-robosuite`` at the repository's root with both robosuite and this
project installed; commands that drive the robosuite world (collecting its datasets, launching its
worker) run there. ``FIRP_ROBOSUITE_PYTHON`` names another interpreter. The scoring service, which needs torch, always runs
in the main environment (``FIRP_SERVICE_PYTHON`` names another).
"""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

__all__ = ["RobosuiteMissing", "has_robosuite", "robosuite_python", "service_python"]

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_VENV = REPO_ROOT / ".venv-robosuite"
MAIN_VENV = REPO_ROOT / ".venv"


class RobosuiteMissing(RuntimeError):
    """No interpreter with robosuite: the message says how to make one."""


def has_robosuite() -> bool:
    """Whether this interpreter can import robosuite (without importing it)."""
    return importlib.util.find_spec("robosuite") is not None


def robosuite_python() -> Path:
    """The interpreter of the robosuite environment (FIRP_ROBOSUITE_PYTHON, else .venv-robosuite's)."""
    configured = os.environ.get("FIRP_ROBOSUITE_PYTHON")
    path = Path(configured) if configured else DEFAULT_VENV / "bin" / "python"
    if not path.exists():
        where = f"FIRP_ROBOSUITE_PYTHON={configured}" if configured else str(path)
        raise RobosuiteMissing(f"--world robosuite: no robosuite environment at {where}; run `make robosuite-install` "
                               "(it makes .venv-robosuite) or set FIRP_ROBOSUITE_PYTHON to an interpreter with "
                               "robosuite and this project installed")
    return path


def service_python() -> Path:
    """An interpreter that runs the scoring service (it needs torch, which the robosuite environment has
    not): this one if it has torch, else FIRP_SERVICE_PYTHON, else the main environment's (.venv)."""
    if importlib.util.find_spec("torch") is not None:
        return Path(sys.executable)
    configured = os.environ.get("FIRP_SERVICE_PYTHON")
    path = Path(configured) if configured else MAIN_VENV / "bin" / "python"
    if not path.exists():
        raise RobosuiteMissing(f"the scoring service needs torch, which {sys.executable} has not, and there is no "
                               f"{path}; run `make install` or set FIRP_SERVICE_PYTHON")
    return path
