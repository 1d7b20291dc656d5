# Sim worker: MuJoCo with headless EGL rendering, no torch. Build from the repository root:
#   docker compose build sim_worker
# Build arguments (compose passes them from FIRP_* variables, see docker-compose.yml):
#   BASE_IMAGE       any Debian-like image with python3 (3.11) and its venv module; default python:3.11-slim
#   PIP_NO_INDEX=1   install from docker/wheels only (an offline build, docker/wheels/README.md)
ARG BASE_IMAGE=python:3.11-slim

# --- build: a virtualenv with the world's dependencies (the wheels stay in this stage) ---
FROM ${BASE_IMAGE} AS build
ARG PIP_NO_INDEX
ARG PIP_FIND_LINKS=/wheels
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PATH=/opt/venv/bin:$PATH
RUN python3 -m venv /opt/venv
WORKDIR /app
COPY docker/wheels /wheels
# The world and the shared core it imports (firp/core, inside the firp package), and the firp command.
# No planner, no method code is run here, no bundle is needed.
COPY pyproject.toml ./
COPY firp ./firp
COPY firp_cli ./firp_cli
COPY world_api ./world_api
COPY sim_worker ./sim_worker
RUN pip install -e ".[sim]"

# --- runtime: the GL libraries MuJoCo's renderer loads by name (the Makefile's APT list) ---
FROM ${BASE_IMAGE}
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PATH=/opt/venv/bin:$PATH MUJOCO_GL=egl
RUN apt-get update \
 && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends \
        libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0 libosmesa6 \
 && rm -rf /var/lib/apt/lists/*
RUN useradd --create-home --uid 10001 --user-group firp
COPY --from=build /opt/venv /opt/venv
COPY --from=build /app /app
WORKDIR /app
USER firp
EXPOSE 8002
ENV FIRP_SIM_HOST=0.0.0.0 FIRP_SIM_PORT=8002
# Ready (200) once the world is built and a warm-up episode rendered; the same probe as docker-compose.yml's.
HEALTHCHECK --interval=10s --timeout=5s --start-period=120s --retries=3 \
    CMD ["python", "-m", "firp.core.probe", "http://127.0.0.1:8002/readyz", "--port-env", "FIRP_SIM_PORT"]
ENTRYPOINT ["firp", "sim"]
