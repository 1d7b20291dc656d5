# Robosuite worker: robosuite 1.5.2 on the MuJoCo it supports (3.3.7) with headless EGL rendering,
# no torch. Build from the repository root:
#   docker compose build robosuite_worker
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    MUJOCO_GL=egl \
    PYOPENGL_PLATFORM=egl

# The GL libraries MuJoCo's renderer loads by name (the Makefile's APT list).
RUN apt-get update \
 && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends \
        libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0 libosmesa6 \
 && rm -rf /var/lib/apt/lists/*

RUN useradd --create-home --uid 10001 --user-group firp
WORKDIR /app

# The robosuite world, the world API and the shared core it imports, and the firp command.
COPY pyproject.toml ./
COPY firp ./firp
COPY firp_cli ./firp_cli
COPY world_api ./world_api
COPY robosuite_worker ./robosuite_worker

RUN pip install -e ".[robosuite]"

USER firp
EXPOSE 8003
ENV FIRP_ROBOSUITE_HOST=0.0.0.0 FIRP_ROBOSUITE_PORT=8003
ENTRYPOINT ["firp", "robosuite"]
