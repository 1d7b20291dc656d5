"""Test-wide setup.

MuJoCo picks its OpenGL backend when it is first imported; headless machines (CI, containers) have
no display, so default to EGL before any test module imports mujoco. The environment still wins,
so a developer can run ``MUJOCO_GL=osmesa pytest``.
"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
