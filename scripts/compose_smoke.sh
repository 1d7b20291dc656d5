#!/usr/bin/env bash
# The compose smoke run: build the three images, bring up `service` and `sim_worker` with the real
# docker-compose client, wait until both are healthy, run three trials of the main job in the planner
# container, check the records and the summary, run them again on three sim worker replicas (profile
# `replicas`), collect four episodes on a Ray cluster of a head and two workers (profile `ray`), compare
# the scores, picks and outcomes with the same trials run without containers and the episodes with the
# same collection without containers, and tear everything down. Every failure names its step.
#
#   bash scripts/compose_smoke.sh              # podman here (no Docker engine), Docker where one runs
#   FIRP_SMOKE_ENGINE=docker bash scripts/compose_smoke.sh
#
# With podman (Debian's, installed here by apt when missing): podman's Docker-compatible API socket
# serves docker-compose; the base image is built from Debian packages with debootstrap (no registry
# needed); every wheel comes from docker/wheels, filled by `pip download` on this machine (an offline
# build: torch is the CPU build); podman without systemd never runs health checks by itself, so this
# script runs them (`podman healthcheck run`) while it waits. With Docker the base is python:3.11-slim
# (FIRP_BASE_IMAGE overrides it) and the engine runs the health checks.
#
# State lives in FIRP_SMOKE_DIR (default .compose-smoke/): podman's storage (the image cache for the
# next run), the logs of each step, and report.json / report.md (image sizes, build and start-up
# times, the score comparison). `--results DIR` also copies the report there.
set -euo pipefail

cd "$(dirname "${BASH_SOURCE[0]}")/.."
ROOT=$PWD
WORK=${FIRP_SMOKE_DIR:-$ROOT/.compose-smoke}
TRIALS=${FIRP_SMOKE_TRIALS:-3}
RESULTS=""
while [ $# -gt 0 ]; do
    case "$1" in
        --results) RESULTS=$2; shift 2 ;;
        -h|--help) sed -n '2,20p' "$0"; exit 0 ;;
        *) echo "compose smoke: unknown argument $1 (known: --results DIR)" >&2; exit 2 ;;
    esac
done
mkdir -p "$WORK/logs"
LOGS=$WORK/logs
export COMPOSE_PROJECT_NAME=firpsmoke
export FIRP_IMAGE_TAG=smoke
export DEBIAN_FRONTEND=noninteractive
export MUJOCO_GL=${MUJOCO_GL:-egl}

STEP="start"
T0=$SECONDS
step() { STEP=$1; echo ">> [$((SECONDS - T0)) s] $STEP"; }
fail() { echo "compose smoke: FAILED at step '$STEP': $*" >&2; exit 1; }
# The failing step's own words where CI shows them: the newest log's last lines and the free disk
# (CI keeps only this script's output, not the logs folder).
show_failure() {
    local newest
    # podman's API service writes its log all along: the newest of the others is the failing step's
    newest=$(ls -t "$LOGS"/*.log 2>/dev/null | grep -v -e '/podman-service.log$' -e '\.first-try\.log$' | head -1) || true
    if [ -n "$newest" ]; then
        echo "compose smoke: last 40 lines of $newest:" >&2
        tail -n 40 "$newest" | sed 's/^/   | /' >&2
    fi
    echo "compose smoke: free disk where the images live: $(df -h --output=avail "$WORK" | tail -1 | tr -d ' ')" >&2
}
on_exit() {
    local status=$?
    trap - EXIT
    if [ "$status" -ne 0 ]; then
        show_failure
        echo "compose smoke: FAILED at step '$STEP' (exit $status); logs in $LOGS" >&2
    fi
    teardown
    exit "$status"
}

# --- the engine --------------------------------------------------------------------------------
ENGINE=${FIRP_SMOKE_ENGINE:-}
if [ -z "$ENGINE" ]; then
    if command -v docker >/dev/null 2>&1 && docker info >/dev/null 2>&1; then ENGINE=docker; else ENGINE=podman; fi
fi
case "$ENGINE" in podman|docker) ;; *) echo "compose smoke: FIRP_SMOKE_ENGINE must be podman or docker, not '$ENGINE'" >&2; exit 2 ;; esac

PODMAN_PID=""
HEALTH_PID=""
teardown() {
    STEP="teardown"
    if [ -n "${COMPOSE[*]:-}" ]; then
        "${COMPOSE[@]}" "${PROFILES[@]}" down -v --remove-orphans >"$LOGS/down.log" 2>&1 || \
            echo "compose smoke: teardown: compose down failed (see $LOGS/down.log)" >&2
    fi
    [ -n "$HEALTH_PID" ] && kill "$HEALTH_PID" 2>/dev/null || true
    if [ -n "$PODMAN_PID" ]; then
        kill "$PODMAN_PID" 2>/dev/null || true; wait "$PODMAN_PID" 2>/dev/null || true
        # podman bind-mounts its overlay folder onto itself and leaves it so; unmounted, `rm -rf
        # .compose-smoke` (make clean) removes everything (the next run mounts it again)
        if mountpoint -q "$WORK/storage/overlay" 2>/dev/null; then umount "$WORK/storage/overlay" 2>/dev/null || true; fi
        PODMAN_PID=""
    fi
}
COMPOSE=()
PROFILES=(--profile planner --profile replicas --profile ray)
trap on_exit EXIT
trap 'exit 130' INT TERM  # an interrupted run tears down too

step "prerequisites"
need=()
command -v docker-compose >/dev/null 2>&1 || need+=(docker-compose)
if [ "$ENGINE" = podman ]; then
    command -v podman >/dev/null 2>&1 || need+=(podman)
    command -v debootstrap >/dev/null 2>&1 || need+=(debootstrap)
fi
if [ ${#need[@]} -gt 0 ]; then
    if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
        echo "   apt-get install ${need[*]}"
        { apt-get update && apt-get install -y "${need[@]}"; } >"$LOGS/apt.log" 2>&1 || fail "apt-get install ${need[*]} (see $LOGS/apt.log)"
    else
        fail "missing ${need[*]} and no apt-get as root to install them"
    fi
fi
make install >"$LOGS/make-install.log" 2>&1 || fail "make install (see $LOGS/make-install.log)"
PY=$ROOT/.venv/bin/python

if [ "$ENGINE" = podman ]; then
    step "podman API socket"
    # This machine refuses podman's default rlimits; storage is ours, so teardown and caching are too.
    printf '[containers]\ndefault_ulimits = []\n' >"$WORK/containers.conf"
    printf '[storage]\ndriver = "overlay"\ngraphroot = "%s/storage"\nrunroot = "%s/run"\n' "$WORK" "$WORK" >"$WORK/storage.conf"
    export CONTAINERS_CONF=$WORK/containers.conf CONTAINERS_STORAGE_CONF=$WORK/storage.conf
    SOCKET=$WORK/podman.sock
    rm -f "$SOCKET"
    podman system service --time=0 "unix://$SOCKET" >"$LOGS/podman-service.log" 2>&1 &
    PODMAN_PID=$!
    for _ in $(seq 1 100); do [ -S "$SOCKET" ] && break; sleep 0.1; done
    [ -S "$SOCKET" ] || fail "podman system service did not open $SOCKET (see $LOGS/podman-service.log)"
    export DOCKER_HOST=unix://$SOCKET
    inspect() { podman "$@"; }
else
    inspect() { docker "$@"; }
fi
COMPOSE=(docker-compose -f "$ROOT/docker-compose.yml")
"${COMPOSE[@]}" "${PROFILES[@]}" down -v --remove-orphans >"$LOGS/down-before.log" 2>&1 || true

step "base image"
if [ "$ENGINE" = podman ] && [ -z "${FIRP_BASE_IMAGE:-}" ]; then
    export FIRP_BASE_IMAGE=localhost/firp-base:bookworm
    if ! podman image exists "$FIRP_BASE_IMAGE"; then
        rm -rf "$WORK/rootfs"
        debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates bookworm "$WORK/rootfs" \
            "${FIRP_DEBIAN_MIRROR:-http://deb.debian.org/debian}" >"$LOGS/debootstrap.log" 2>&1 \
            || fail "debootstrap bookworm (see $LOGS/debootstrap.log)"
        tar -C "$WORK/rootfs" -c . | podman import - "$FIRP_BASE_IMAGE" >"$LOGS/import.log" 2>&1 \
            || fail "podman import of the debootstrap root (see $LOGS/import.log)"
        rm -rf "$WORK/rootfs"
    fi
fi
echo "   base: ${FIRP_BASE_IMAGE:-python:3.11-slim}"

step "wheels (pip download into docker/wheels)"
# The images' every dependency, resolved here as `make install` resolves them (torch: the CPU build).
"$ROOT/.venv/bin/pip" download -q -d "$ROOT/docker/wheels" setuptools wheel "torch==2.13.0" ".[service,sim,planner,ray]" \
    >"$LOGS/pip-download.log" 2>&1 || fail "pip download (see $LOGS/pip-download.log)"
# globs, not `ls | grep -q`: under pipefail grep's early exit would kill ls with SIGPIPE once the listing
# outgrows one pipe write, and a wheel that is there would read as missing
compgen -G "$ROOT/docker/wheels/torch-2.13.0+cpu-*.whl" >/dev/null || fail "docker/wheels has no CPU build of torch 2.13.0"
compgen -G "$ROOT/docker/wheels/nvidia*" >/dev/null && fail "docker/wheels holds CUDA wheels (nvidia-*)"
export FIRP_PIP_NO_INDEX=1

declare -A BUILD_S SIZE_MB READY_S STOP_S EXIT_CODE
declare -A IMAGE=([service]=firp-service [sim_worker]=firp-sim-worker [planner]=firp-planner [ray_head]=firp-planner-ray)
for name in service sim_worker planner ray_head; do
    step "build $name"
    start=$SECONDS
    # one retry: a build that fails once (a registry or mirror hiccup, a full layer cache) says why and
    # goes again; the second failure is the step's
    if ! "${COMPOSE[@]}" "${PROFILES[@]}" build "$name" >"$LOGS/build-$name.log" 2>&1; then
        echo "   build $name failed once; its log's last lines:"
        tail -n 20 "$LOGS/build-$name.log" | sed 's/^/   | /'
        echo "   free disk: $(df -h --output=avail "$WORK" | tail -1 | tr -d ' '); retrying"
        mv "$LOGS/build-$name.log" "$LOGS/build-$name.first-try.log"
        "${COMPOSE[@]}" "${PROFILES[@]}" build "$name" >"$LOGS/build-$name.log" 2>&1 \
            || fail "compose build $name, twice (see $LOGS/build-$name.log)"
    fi
    BUILD_S[$name]=$((SECONDS - start))
    image="${IMAGE[$name]}:$FIRP_IMAGE_TAG"
    bytes=$(inspect image inspect --format '{{.Size}}' "$image") || fail "no image $image after the build"
    SIZE_MB[$name]=$((bytes / 1000000))
    if [ "$ENGINE" = podman ] && [ "$name" != planner ]; then
        # the build stage's images (a venv and the wheels, ~1 GB per image) are dangling once the runtime
        # stage has its copy; podman's storage is ours, so drop them: four builds' worth filled ~4 GB more.
        # Not after the planner: ray_head builds on the planner's stages, and a rebuilt build stage would
        # make it a second full virtualenv instead of the planner's layers plus Ray.
        inspect image prune -f >>"$LOGS/prune.log" 2>&1 || echo "   (podman image prune failed, see $LOGS/prune.log)"
    fi
    echo "   $image: ${SIZE_MB[$name]} MB in ${BUILD_S[$name]} s (free disk $(df -h --output=avail "$WORK" | tail -1 | tr -d ' '))"
done

if [ "$ENGINE" = podman ]; then
    echo "   image storage: $(du -sh "$WORK/storage" 2>/dev/null | cut -f1) for the four images and their base"
fi

step "image contents"
# What each image must not contain: the service no CUDA and no MuJoCo; the sim worker, the planner and
# ray_head no torch (ray_head: Ray beside the planner).
: >"$LOGS/contents.log"
probe() {  # probe SERVICE PYTHON-CODE
    "${COMPOSE[@]}" "${PROFILES[@]}" run --rm -T --no-deps --entrypoint python "$1" -c "$2" >>"$LOGS/contents.log" 2>&1 \
        || fail "$1's image: $(tail -1 "$LOGS/contents.log")"
}
no_cuda='import glob, importlib.util as u, sys, torch
bad = glob.glob("/opt/venv/**/libcudart*", recursive=True) + glob.glob("/opt/venv/**/nvidia", recursive=True)
assert not bad and not torch.cuda.is_available() and "+cpu" in torch.__version__, f"CUDA in the image: {bad[:3]} {torch.__version__}"
assert u.find_spec("mujoco") is None, "mujoco is installed"; print("service: torch", torch.__version__, "no CUDA, no mujoco")'
no_torch='import importlib.util as u, mujoco; assert u.find_spec("torch") is None, "torch is installed"; print("no torch, mujoco", mujoco.__version__)'
probe service "$no_cuda"
probe sim_worker "$no_torch"
probe planner "$no_torch"
# ray_head: the planner's image plus Ray (its planner-ray stage), still no torch
probe ray_head 'import importlib.util as u, mujoco, ray, planner_client; assert u.find_spec("torch") is None, "torch is installed"; print("ray", ray.__version__, "on the planner, no torch")'
grep -v '^Creating' "$LOGS/contents.log" | sed 's/^/   /'

step "up service sim_worker"
if [ "$ENGINE" = podman ]; then
    # podman without systemd never runs health checks on its own: run them, as the engine would.
    ( while true; do
        for id in $("${COMPOSE[@]}" "${PROFILES[@]}" ps -q 2>/dev/null); do podman healthcheck run "$id" >/dev/null 2>&1 || true; done
        sleep 2
      done ) >/dev/null 2>&1 &
    HEALTH_PID=$!
fi
start_ms=$(date +%s%3N)
"${COMPOSE[@]}" up -d service sim_worker >"$LOGS/up.log" 2>&1 || fail "compose up -d service sim_worker (see $LOGS/up.log)"

step "wait until healthy"
deadline=$((SECONDS + ${FIRP_SMOKE_READY_TIMEOUT:-300}))
declare -A PORT=([service]=8001 [sim_worker]=8002)
for name in service sim_worker; do
    # Start-up time: from `compose up` to the first 200 on /readyz from the host.
    until curl -sf "http://127.0.0.1:${PORT[$name]}/readyz" >/dev/null 2>&1; do
        [ $SECONDS -lt $deadline ] || { "${COMPOSE[@]}" logs "$name" >"$LOGS/$name.log" 2>&1; fail "$name not ready (see $LOGS/$name.log)"; }
        sleep 0.2
    done
    READY_S[$name]=$(awk -v a="$start_ms" -v b="$(date +%s%3N)" 'BEGIN { printf "%.1f", (b - a) / 1000 }')
    id=$("${COMPOSE[@]}" ps -q "$name")
    until [ "$(inspect inspect --format '{{.State.Health.Status}}' "$id")" = healthy ]; do
        [ $SECONDS -lt $deadline ] || fail "$name ready but its health check never turned healthy"
        sleep 0.5
    done
    echo "   $name ready after ${READY_S[$name]} s, healthy"
done

step "planner run --trials $TRIALS"
start=$SECONDS
"${COMPOSE[@]}" run --rm -T planner run --trials "$TRIALS" --out /app/runs/smoke.jsonl >"$LOGS/planner.log" 2>&1 \
    || fail "compose run planner run --trials $TRIALS (see $LOGS/planner.log)"
PLANNER_S=$((SECONDS - start))
tail -n 25 "$LOGS/planner.log" | sed 's/^/   /'

step "fetch the records"
rm -rf "$WORK/container-run" && mkdir -p "$WORK/container-run"
fetch_run() {  # fetch_run FILE...: trial records out of the planner's volume
    for file in "$@"; do
        "${COMPOSE[@]}" "${PROFILES[@]}" run --rm -T --no-deps --entrypoint cat planner "/app/runs/$file" \
            >"$WORK/container-run/$file" 2>"$LOGS/fetch.log" || fail "no /app/runs/$file in the planner's volume"
    done
}
fetch_run smoke.jsonl smoke.summary.json smoke.summary.md

step "replicas: up sim_worker_2 sim_worker_3"
"${COMPOSE[@]}" --profile replicas up -d sim_worker_2 sim_worker_3 >"$LOGS/up-replicas.log" 2>&1 \
    || fail "compose up -d sim_worker_2 sim_worker_3 (see $LOGS/up-replicas.log)"
deadline=$((SECONDS + ${FIRP_SMOKE_READY_TIMEOUT:-300}))
for name in sim_worker_2 sim_worker_3; do
    id=$("${COMPOSE[@]}" --profile replicas ps -q "$name")
    until [ "$(inspect inspect --format '{{.State.Health.Status}}' "$id")" = healthy ]; do
        [ $SECONDS -lt $deadline ] || { "${COMPOSE[@]}" --profile replicas logs "$name" >"$LOGS/$name.log" 2>&1; fail "$name never turned healthy (see $LOGS/$name.log)"; }
        sleep 0.5
    done
done
echo "   three sim workers healthy"

step "replicas: planner_replicas run --trials $TRIALS"
start=$SECONDS
"${COMPOSE[@]}" --profile replicas run --rm -T planner_replicas run --trials "$TRIALS" --out /app/runs/replicas.jsonl \
    >"$LOGS/planner-replicas.log" 2>&1 || fail "compose run planner_replicas (see $LOGS/planner-replicas.log)"
REPLICAS_S=$((SECONDS - start))
fetch_run replicas.jsonl
"${COMPOSE[@]}" --profile replicas stop sim_worker_2 sim_worker_3 >>"$LOGS/stop.log" 2>&1 || fail "compose stop the replicas"
echo "   $TRIALS trials on three workers in $REPLICAS_S s"

step "ray: a collection on a head and two workers"
RAY_EPISODES=4
start=$SECONDS
FIRP_RAY_EPISODES=$RAY_EPISODES FIRP_RAY_ACTORS=2 FIRP_RAY_WORKER_CPUS=1 \
    "${COMPOSE[@]}" --profile ray up --scale ray_worker=2 --exit-code-from ray_head ray_head ray_worker \
    >"$LOGS/ray.log" 2>&1 || fail "compose --profile ray up (see $LOGS/ray.log)"
RAY_S=$((SECONDS - start))
"${COMPOSE[@]}" --profile ray run --rm -T --no-deps --entrypoint cat ray_head /app/data/stacking.h5 \
    >"$WORK/container-run/ray-stacking.h5" 2>"$LOGS/fetch-ray.log" || fail "no /app/data/stacking.h5 in the volume ray-data"
nodes=$(grep -c "Ray runtime started\|Ray runtime started." "$LOGS/ray.log" || true)
echo "   $RAY_EPISODES episodes in $RAY_S s ($nodes Ray nodes started)"

step "stop (drain)"
for name in service sim_worker; do
    id=$("${COMPOSE[@]}" ps -q "$name")
    start=$SECONDS
    "${COMPOSE[@]}" stop "$name" >>"$LOGS/stop.log" 2>&1 || fail "compose stop $name (see $LOGS/stop.log)"
    STOP_S[$name]=$((SECONDS - start))
    EXIT_CODE[$name]=$(inspect inspect --format '{{.State.ExitCode}}' "$id")
    echo "   $name stopped in ${STOP_S[$name]} s, exit code ${EXIT_CODE[$name]}"
    [ "${EXIT_CODE[$name]}" = 0 ] || fail "$name exited ${EXIT_CODE[$name]} on SIGTERM (not a clean drain)"
done
teardown
COMPOSE=()

step "the same trials without containers"
rm -f "$WORK/host.jsonl"
"$ROOT/.venv/bin/firp" run --trials "$TRIALS" --out "$WORK/host.jsonl" >"$LOGS/host-run.log" 2>&1 \
    || fail "firp run --trials $TRIALS (see $LOGS/host-run.log)"

step "the same episodes without containers"
rm -f "$WORK/host-stacking.h5"
"$ROOT/.venv/bin/firp" collect --task stacking --episodes "$RAY_EPISODES" --workers 2 --no-progress \
    --out "$WORK/host-stacking.h5" >"$LOGS/host-collect.log" 2>&1 || fail "firp collect (see $LOGS/host-collect.log)"

step "compare"
sizes=""; for n in service sim_worker planner ray_head; do sizes+="$n=${SIZE_MB[$n]}:${BUILD_S[$n]} "; done
ready=""; for n in service sim_worker; do ready+="$n=${READY_S[$n]}:${STOP_S[$n]}:${EXIT_CODE[$n]} "; done
"$PY" "$ROOT/scripts/compose_smoke_report.py" --container "$WORK/container-run/smoke.jsonl" --host "$WORK/host.jsonl" \
    --trials "$TRIALS" --engine "$ENGINE" --base "${FIRP_BASE_IMAGE:-python:3.11-slim}" --images $sizes --servers $ready \
    --planner-seconds "$PLANNER_S" --replicas "$WORK/container-run/replicas.jsonl" --replicas-seconds "$REPLICAS_S" \
    --ray-dataset "$WORK/container-run/ray-stacking.h5" --host-dataset "$WORK/host-stacking.h5" --ray-seconds "$RAY_S" \
    --seconds $((SECONDS - T0)) --out "$WORK" || fail "the container runs differ from the runs without containers"
if [ -n "$RESULTS" ]; then mkdir -p "$RESULTS" && cp "$WORK/report.json" "$WORK/report.md" "$RESULTS/"; fi
STEP="done"
echo "compose smoke: OK in $((SECONDS - T0)) s (report: $WORK/report.md)"
