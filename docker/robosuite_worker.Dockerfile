# Robosuite worker: robosuite 1.5.2 on the MuJoCo it supports (3.3.7) with headless EGL rendering,
# no torch. Build from the repository root:
#   docker compose --profile robosuite build robosuite_worker
# Build arguments (compose passes them from FIRP_* variables, see docker-compose.yml):
#   BASE_IMAGE       any Debian-like image with python3 (3.11) and its venv module; default python:3.11-slim
#   PIP_NO_INDEX=1   install from docker/wheels only (an offline build, docker/wheels/README.md; the
#                    wheels then come from `pip download -d docker/wheels setuptools wheel ".[robosuite]"`)
ARG BASE_IMAGE=python:3.11-slim

# --- build: a virtualenv with robosuite and the world API (the wheels stay in this stage) ---
FROM ${BASE_IMAGE} AS build
ARG PIP_NO_INDEX
ARG PIP_FIND_LINKS=/wheels
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PATH=/opt/venv/bin:$PATH
# robosuite pulls pynput -> evdev, published as source only: its build needs a C compiler, the kernel's
# input headers and Python's (python3-dev where the base lacks Python.h). Build stage only.
RUN apt-get update \
 && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends gcc libc6-dev linux-libc-dev \
 && if ! python3 -c "import os, sys, sysconfig; sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()['include'], 'Python.h')))"; then \
        DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends python3-dev; fi \
 && rm -rf /var/lib/apt/lists/*
RUN python3 -m venv /opt/venv
WORKDIR /app
COPY docker/wheels /wheels
# The robosuite world, the world API and the shared core it imports, and the firp command.
COPY pyproject.toml ./
COPY firp ./firp
COPY firp_cli ./firp_cli
COPY world_api ./world_api
COPY robosuite_worker ./robosuite_worker
RUN pip install -e ".[robosuite]"

# --- runtime: the GL libraries MuJoCo's renderer loads by name (the Makefile's APT list), libGL itself
# and GLib, which robosuite's imports load even when rendering through EGL (PyOpenGL, OpenCV) ---
FROM ${BASE_IMAGE}
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PATH=/opt/venv/bin:$PATH MUJOCO_GL=egl PYOPENGL_PLATFORM=egl
RUN apt-get update \
 && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends \
        libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0 libosmesa6 libgl1 libglib2.0-0 \
 && rm -rf /var/lib/apt/lists/*
RUN useradd --create-home --uid 10001 --user-group firp
COPY --from=build /opt/venv /opt/venv
COPY --from=build /app /app
WORKDIR /app
USER firp
EXPOSE 8003
ENV FIRP_ROBOSUITE_HOST=0.0.0.0 FIRP_ROBOSUITE_PORT=8003
# Ready (200) once robosuite's environments are built and warmed up; the same probe as docker-compose.yml's.
HEALTHCHECK --interval=10s --timeout=5s --start-period=120s --retries=3 \
    CMD ["python", "-m", "firp.core.probe", "http://127.0.0.1:8003/readyz", "--port-env", "FIRP_ROBOSUITE_PORT"]
ENTRYPOINT ["firp", "robosuite"]
