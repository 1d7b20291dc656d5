# Planner client (the main job): TAMP planner + trial loop, no torch. Talks to the sim worker and
# the scoring service over HTTP; MuJoCo is here for the planner's IK on the robot model (and the
# embedded simulator when no --sim URL is given). Build from the repository root:
#   docker compose build planner
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    MUJOCO_GL=egl

RUN apt-get update \
 && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends \
        libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0 libosmesa6 \
 && rm -rf /var/lib/apt/lists/*

RUN useradd --create-home --uid 10001 --user-group firp
WORKDIR /app

COPY pyproject.toml ./
COPY firp ./firp
COPY firp_cli ./firp_cli
COPY world_api ./world_api
COPY sim_worker ./sim_worker
COPY planner_client ./planner_client

RUN pip install -e ".[planner]" \
 && mkdir -p /app/runs && chown firp:firp /app/runs

USER firp
ENTRYPOINT ["firp"]
CMD ["run", "--trials", "50"]
