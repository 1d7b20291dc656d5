# Scoring service: CPU-only torch, no MuJoCo. Build from the repository root:
#   docker compose build service
# Build arguments (compose passes them from FIRP_* variables, see docker-compose.yml):
#   BASE_IMAGE       any Debian-like image with python3 (3.11) and its venv module; default python:3.11-slim
#   TORCH_INDEX_URL  where the CPU build of torch comes from; default the PyTorch CPU index
#   PIP_NO_INDEX=1   install from docker/wheels only (an offline build, docker/wheels/README.md)
ARG BASE_IMAGE=python:3.11-slim

# --- build: a virtualenv with the service's dependencies (the wheels stay in this stage) ---
FROM ${BASE_IMAGE} AS build
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
ARG PIP_NO_INDEX
ARG PIP_FIND_LINKS=/wheels
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PATH=/opt/venv/bin:$PATH
RUN python3 -m venv /opt/venv
WORKDIR /app
COPY docker/wheels /wheels
# Only what the service imports: the method (with the shared core), the service, the firp command
# and the shipped bundles (models/, found as /app/models).
COPY pyproject.toml ./
COPY firp ./firp
COPY firp_cli ./firp_cli
COPY service ./service
COPY models ./models
# The README's install steps: CPU torch first (pinned; from the CPU index, so pip cannot pull a
# multi-GB CUDA build), then the service extra.
RUN pip install --index-url "$TORCH_INDEX_URL" torch==2.13.0 \
 && pip install -e ".[service]"

# --- runtime ---
FROM ${BASE_IMAGE}
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PATH=/opt/venv/bin:$PATH
RUN useradd --create-home --uid 10001 --user-group firp
COPY --from=build /opt/venv /opt/venv
COPY --from=build /app /app
WORKDIR /app
USER firp
EXPOSE 8001
ENV FIRP_SERVICE_HOST=0.0.0.0 FIRP_SERVICE_PORT=8001
# Ready (200) only once the bundle is loaded and warmed up; the same probe as docker-compose.yml's.
HEALTHCHECK --interval=10s --timeout=5s --start-period=120s --retries=3 \
    CMD ["python", "-m", "firp.core.probe", "http://127.0.0.1:8001/readyz", "--port-env", "FIRP_SERVICE_PORT"]
ENTRYPOINT ["firp", "serve"]
