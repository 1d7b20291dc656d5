# Scoring service: CPU-only torch, no MuJoCo. Build from the repository root:
#   docker compose build service
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

RUN useradd --create-home --uid 10001 --user-group firp
WORKDIR /app

# Only what the service imports: the shared contract/method package and the service itself.
COPY pyproject.toml ./
COPY firp ./firp
COPY service ./service

# The README's install steps: CPU torch first (pinned; from the CPU index, so pip cannot pull a
# multi-GB CUDA build), then the service extra.
RUN pip install --index-url https://download.pytorch.org/whl/cpu torch==2.13.0 \
 && pip install -e ".[service]"

USER firp
EXPOSE 8001
ENTRYPOINT ["python", "-m", "service"]
CMD ["--host", "0.0.0.0", "--port", "8001", "--bundle", "firp/bundles/stacking"]
