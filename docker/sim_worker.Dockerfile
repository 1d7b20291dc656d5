# Sim worker: MuJoCo with headless EGL rendering, no torch. Build from the repository root:
#   docker compose build sim_worker
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    MUJOCO_GL=egl

# The GL libraries MuJoCo's renderer loads by name (the README's / Makefile's APT list).
RUN apt-get update \
 && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends \
        libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0 libosmesa6 \
 && rm -rf /var/lib/apt/lists/*

RUN useradd --create-home --uid 10001 --user-group firp
WORKDIR /app

# The world and the shared core it imports (firp/core, inside the firp package), and the firp command.
# No planner, no method code is run here, no bundle is needed.
COPY pyproject.toml ./
COPY firp ./firp
COPY firp_cli ./firp_cli
COPY world_api ./world_api
COPY sim_worker ./sim_worker

RUN pip install -e ".[sim]"

USER firp
EXPOSE 8002
ENV FIRP_SIM_HOST=0.0.0.0 FIRP_SIM_PORT=8002
ENTRYPOINT ["firp", "sim"]
