# Scoring service: CPU-only torch, no MuJoCo. Build from the repository root:
#   docker compose build service
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

RUN useradd --create-home --uid 10001 --user-group firp
WORKDIR /app

# Only what the service imports: the method (with the shared core), the service, the firp command
# and the shipped bundles (models/, found as /app/models).
COPY pyproject.toml ./
COPY firp ./firp
COPY firp_cli ./firp_cli
COPY service ./service
COPY models ./models

# The README's install steps: CPU torch first (pinned; from the CPU index, so pip cannot pull a
# multi-GB CUDA build), then the service extra.
RUN pip install --index-url https://download.pytorch.org/whl/cpu torch==2.13.0 \
 && pip install -e ".[service]"

USER firp
EXPOSE 8001
ENV FIRP_SERVICE_HOST=0.0.0.0 FIRP_SERVICE_PORT=8001
ENTRYPOINT ["firp", "serve"]
