# Planner client (the main job): TAMP planner + trial loop, no torch. Talks to the sim worker and
# the scoring service over HTTP; MuJoCo is here for the planner's IK on the robot model (and the
# embedded simulator when no --sim URL is given). Build from the repository root:
#   docker compose build planner
# Build arguments (compose passes them from FIRP_* variables, see docker-compose.yml):
#   BASE_IMAGE       any Debian-like image with python3 (3.11) and its venv module; default python:3.11-slim
#   PIP_NO_INDEX=1   install from docker/wheels only (an offline build, docker/wheels/README.md)
#   EXTRAS           the extras installed (default planner)
# Targets: the default is the planner; `--target planner-ray` adds Ray (the `ray` extra) on top of the
# planner's own layers, so the two images share everything but Ray's packages (~0.3 GB, not a second
# 1.1 GB virtualenv): compose's Ray services build that target.
ARG BASE_IMAGE=python:3.11-slim

# --- build: a virtualenv with the planner's dependencies (the wheels stay in this stage) ---
FROM ${BASE_IMAGE} AS build
ARG PIP_NO_INDEX
ARG PIP_FIND_LINKS=/wheels
ARG EXTRAS=planner
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PATH=/opt/venv/bin:$PATH
RUN python3 -m venv /opt/venv
WORKDIR /app
COPY docker/wheels /wheels
COPY pyproject.toml ./
COPY firp ./firp
COPY firp_cli ./firp_cli
COPY world_api ./world_api
COPY sim_worker ./sim_worker
COPY planner_client ./planner_client
RUN pip install -e ".[$EXTRAS]"

# --- ray-wheels: the `ray` extra's wheels (and its dependencies'), set apart for the planner-ray stage ---
FROM build AS ray-wheels
ARG PIP_NO_INDEX
ARG PIP_FIND_LINKS=/wheels
RUN python3 -c "import tomllib; print(*tomllib.load(open('pyproject.toml', 'rb'))['project']['optional-dependencies']['ray'], sep='\n')" \
        >/ray-requirements.txt \
 && pip download -q -d /ray-wheels -r /ray-requirements.txt

# --- planner (runtime): the GL libraries MuJoCo's renderer loads by name (the Makefile's APT list) ---
FROM ${BASE_IMAGE} AS planner
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PATH=/opt/venv/bin:$PATH MUJOCO_GL=egl
RUN apt-get update \
 && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends \
        libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0 libosmesa6 \
 && rm -rf /var/lib/apt/lists/*
RUN useradd --create-home --uid 10001 --user-group firp
COPY --from=build /opt/venv /opt/venv
COPY --from=build /app /app
# Trial records land in /app/runs (compose mounts the volume planner-runs there).
RUN mkdir -p /app/runs && chown firp:firp /app/runs
WORKDIR /app
USER firp
ENTRYPOINT ["firp"]
CMD ["run", "--trials", "50"]

# --- planner-ray: the planner plus Ray, installed into the planner's virtualenv from the set-apart wheels ---
FROM planner AS planner-ray
USER root
COPY --from=ray-wheels /ray-requirements.txt /ray-wheels /tmp/ray-wheels/
RUN pip install --no-cache-dir --no-index --find-links /tmp/ray-wheels -r /tmp/ray-wheels/ray-requirements.txt \
 && rm -rf /tmp/ray-wheels
USER firp

# --- the default target: the planner alone ---
FROM planner
