"""docker-compose.yml and the Dockerfiles, checked without a Docker engine.

``docker-compose config`` (Debian's v1 package, installed by the Makefile) validates the file
against the Compose schema when the binary exists; the structural checks below run everywhere and
pin what the schema cannot: health checks on /readyz, start order on health, non-root users, the
planner behind a profile, torch only in the service image, and install steps the README shows.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "docker-compose.yml"
DOCKERFILES = {"service": "docker/service.Dockerfile", "sim_worker": "docker/sim_worker.Dockerfile",
               "robosuite_worker": "docker/robosuite_worker.Dockerfile", "planner": "docker/planner.Dockerfile"}
GL_LIBS = "libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0 libosmesa6"


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def _dockerfile(name: str) -> str:
    return (ROOT / DOCKERFILES[name]).read_text()


def _run_steps(name: str) -> list[str]:
    """The Dockerfile's RUN instructions, continuation lines joined."""
    joined = re.sub(r"\\\n\s*", " ", _dockerfile(name))
    return [line[4:] for line in joined.splitlines() if line.startswith("RUN ")]


@pytest.mark.skipif(shutil.which("docker-compose") is None, reason="docker-compose (v1) is not installed "
                    "(`make system-deps` installs it on Debian as root)")
def test_docker_compose_config_accepts_the_file():
    out = subprocess.run(["docker-compose", "-f", str(COMPOSE), "config", "-q"], capture_output=True, text=True,
                         cwd=ROOT, timeout=60)
    assert out.returncode == 0, out.stderr


def _build_args(name: str) -> dict[str, str | None]:
    """The Dockerfile's ARGs (before or after its first FROM) with their defaults."""
    return {m.group(1): m.group(2) for m in re.finditer(r"^ARG (\w+)(?:=(\S+))?$", _dockerfile(name), re.M)}


#: the services beyond the four parts: replicas of a part (same build), and the Ray cluster's nodes
REPLICAS = {"sim_worker_2": "sim_worker", "sim_worker_3": "sim_worker", "planner_replicas": "planner"}
RAY = ("ray_head", "ray_worker")


def test_services_build_from_the_dockerfiles(compose):
    assert set(compose["services"]) == set(DOCKERFILES) | set(REPLICAS) | set(RAY)
    for name, service in compose["services"].items():
        if name == "ray_worker":  # runs the image ray_head builds
            assert service["image"] == compose["services"]["ray_head"]["image"] and "build" not in service
            continue
        part = "planner" if name == "ray_head" else REPLICAS.get(name, name)
        build = service["build"]
        assert (build["context"], build["dockerfile"]) == (".", DOCKERFILES[part])
        assert (ROOT / DOCKERFILES[part]).is_file()
        # every build argument compose passes is one the Dockerfile declares, each from a FIRP_* variable
        assert set(build["args"]) <= set(_build_args(part)), (name, set(build["args"]) - set(_build_args(part)))
        assert {"BASE_IMAGE", "PIP_NO_INDEX"} <= set(build["args"])
        assert all(str(v).startswith("${FIRP_") for v in build["args"].values())
        # ray_head builds the planner's Dockerfile to its Ray stage (the planner's layers plus Ray); the
        # others build the default target
        assert build.get("target") == ("planner-ray" if name == "ray_head" else None)
        if "target" in build:
            assert re.search(rf"^FROM \S+ AS {build['target']}$", _dockerfile(part), re.M)
        image = f"firp-{part.replace('_', '-')}{'-ray' if name == 'ray_head' else ''}:${{FIRP_IMAGE_TAG:-latest}}"
        assert service["image"] == image


@pytest.mark.parametrize("name", list(DOCKERFILES))
def test_wheels_and_build_tools_stay_in_the_build_stage(name):
    """docker/wheels and pip's work in the build stage; the runtime copies only the venv and /app."""
    text = _dockerfile(name)
    stages = re.split(r"^FROM ", text, flags=re.M)[1:]
    assert stages[0].startswith("${BASE_IMAGE} AS build") and "COPY docker/wheels /wheels" in stages[0]
    runtime = [stage for stage in stages if stage.startswith("${BASE_IMAGE}")][1:]
    assert len(runtime) == 1, "one runtime stage from the base image"
    assert "/wheels" not in runtime[0] and "pip install" not in runtime[0]
    if name == "planner":
        # the Ray stage adds only Ray's own wheels, set apart in a stage of their own, and leaves none behind
        ray = next(stage for stage in stages if stage.startswith("planner AS planner-ray"))
        assert "COPY --from=ray-wheels" in ray and "--no-index --find-links /tmp/ray-wheels" in ray
        assert "rm -rf /tmp/ray-wheels" in ray and "docker/wheels" not in ray
        assert stages[-1].strip() == "planner", "the default target is the planner alone"
    else:
        assert len(stages) == 2
    assert _build_args(name).get("PIP_FIND_LINKS") == "/wheels"
    assert (ROOT / "docker/wheels/README.md").is_file()  # the folder exists in a fresh clone, so COPY works


def test_health_checks_are_in_the_images_too(compose):
    """`docker run` without compose gets the same /readyz probe as docker-compose.yml's."""
    for name in ("service", "sim_worker", "robosuite_worker"):
        joined = re.sub(r"\\\n\s*", " ", _dockerfile(name))
        check = next((line for line in joined.splitlines() if line.startswith("HEALTHCHECK ")), "")
        assert "/readyz" in check and PORT_VARIABLE[name] in check and "--start-period=120s" in check, name
        # exec form, no argument with a space: podman's Docker API splits a CMD's arguments at spaces
        command = json.loads(check.split(" CMD ", 1)[1])
        assert command[:3] == ["python", "-m", "firp.core.probe"] and not any(" " in arg for arg in command)


PORT_VARIABLE = {"service": "FIRP_SERVICE_PORT", "sim_worker": "FIRP_SIM_PORT", "robosuite_worker": "FIRP_ROBOSUITE_PORT"}


def _port(compose: dict, name: str) -> str:
    return str(compose["services"][name]["environment"][PORT_VARIABLE[name]])


@pytest.mark.parametrize("name", ["service", "sim_worker", "robosuite_worker"])
def test_servers_are_healthy_only_when_ready(compose, name):
    service = compose["services"][name]
    port = _port(compose, name)
    assert service["healthcheck"]["test"] == ["CMD", "python", "-m", "firp.core.probe", f"http://127.0.0.1:{port}/readyz"]
    assert "start_period" in service["healthcheck"]
    assert ("profiles" in service) == (name == "robosuite_worker")  # robosuite's world only when asked for


def test_planner_waits_for_healthy_services_and_is_behind_a_profile(compose):
    planner = compose["services"]["planner"]
    assert planner["profiles"] == ["planner"]
    assert planner["depends_on"] == {"service": {"condition": "service_healthy"},
                                     "sim_worker": {"condition": "service_healthy"}}
    env = planner["environment"]
    assert env["FIRP_PLANNER_SIM_URL"] == f"http://sim_worker:{_port(compose, 'sim_worker')}"
    assert env["FIRP_PLANNER_SERVICE_URL"] == f"http://service:{_port(compose, 'service')}"
    # `docker compose run planner run --trials 50`: the image's entry point is the firp command
    assert re.search(r'^ENTRYPOINT \["firp"\]$', _dockerfile("planner"), re.M)
    assert planner["command"][0] == "run"


def test_compose_sets_only_variables_the_settings_read(compose):
    """One settings scheme: every FIRP_* variable compose sets is a field of that part's pydantic settings."""
    from planner_client.settings import PlannerSettings
    from service.settings import ServiceSettings
    from sim_worker.settings import SimWorkerSettings

    from robosuite_worker.settings import RobosuiteSettings

    settings = {"service": ServiceSettings, "sim_worker": SimWorkerSettings, "planner": PlannerSettings,
                "robosuite_worker": RobosuiteSettings, "sim_worker_2": SimWorkerSettings,
                "sim_worker_3": SimWorkerSettings, "planner_replicas": PlannerSettings}
    for name, cls in settings.items():
        prefix = cls.model_config["env_prefix"]
        known = {prefix + field.upper() for field in cls.model_fields}
        used = {k for k in compose["services"][name].get("environment", {}) if k.startswith("FIRP_")}
        assert used and used <= known, (name, sorted(used - known))
    assert "FIRP_SERVICE_BUNDLE" in compose["services"]["service"]["environment"]


@pytest.mark.parametrize("name, entry", [("service", '["firp", "serve"]'), ("sim_worker", '["firp", "sim"]'),
                                         ("robosuite_worker", '["firp", "robosuite"]')])
def test_servers_start_as_the_firp_command_configured_by_the_environment(compose, name, entry):
    assert re.search(rf"^ENTRYPOINT {re.escape(entry)}$", _dockerfile(name), re.M)
    assert "command" not in compose["services"][name]


@pytest.mark.parametrize("name", list(DOCKERFILES))
def test_images_are_slim_and_run_as_a_non_root_user(compose, name):
    text = _dockerfile(name)
    assert _build_args(name)["BASE_IMAGE"] == "python:3.11-slim"  # the default; a local Debian base here
    assert re.search(r"^FROM \$\{BASE_IMAGE\}( AS (?!build\b)[\w-]+)?$", text, re.M)  # the runtime stage
    users = re.findall(r"^USER (\S+)", text, re.M)
    assert users and users[-1] not in ("root", "0", "0:0")
    user = str(compose["services"][name].get("user", users[-1]))
    assert user.split(":")[0] not in ("root", "0")


@pytest.mark.parametrize("name,extra", [("service", "service"), ("sim_worker", "sim"), ("robosuite_worker", "robosuite"),
                                        ("planner", "planner")])
def test_images_install_like_the_readme(name, extra):
    steps = " && ".join(_run_steps(name))
    for arg, default in _build_args(name).items():  # a build argument's default is what a plain build runs
        if default is not None and arg != "TORCH_INDEX_URL":
            steps = steps.replace(f"${arg}", default)
    readme = (ROOT / "README.md").read_text()
    install = f'pip install -e ".[{extra}]"'
    assert install in steps and install in readme
    assert ("torch" in steps) == (name == "service")  # torch only where it is used
    if name == "service":
        cpu_torch = "pip install --index-url https://download.pytorch.org/whl/cpu torch==2.13.0"
        index = _build_args(name)["TORCH_INDEX_URL"]
        assert steps.replace('"$TORCH_INDEX_URL"', index).count(cpu_torch) == 1 and cpu_torch in readme


@pytest.mark.parametrize("name", ["sim_worker", "robosuite_worker", "planner"])
def test_mujoco_images_have_the_gl_libraries_and_egl(compose, name):
    assert any(GL_LIBS in step for step in _run_steps(name))
    assert re.search(r"MUJOCO_GL=egl", _dockerfile(name))
    assert compose["services"][name]["environment"]["MUJOCO_GL"] == "egl"


def test_makefile_installs_docker_compose_for_ci():
    apt = re.search(r"^APT_PACKAGES := (.*)$", (ROOT / "Makefile").read_text(), re.M).group(1).split()
    assert "docker-compose" in apt and set(GL_LIBS.split()) <= set(apt)


def _seconds(duration: str) -> float:
    """compose's duration (``30s``, ``1m30s``) in seconds."""
    parts = re.fullmatch(r"(?:(\d+)m)?(?:(\d+(?:\.\d+)?)s)?", duration)
    assert parts and duration, f"not a compose duration: {duration!r}"
    return 60 * float(parts.group(1) or 0) + float(parts.group(2) or 0)


@pytest.mark.parametrize("name, variable", [("service", "FIRP_SERVICE_DRAIN_GRACE_S"),
                                            ("sim_worker", "FIRP_SIM_DRAIN_GRACE_S"),
                                            ("robosuite_worker", "FIRP_ROBOSUITE_DRAIN_GRACE_S")])
def test_each_drain_ends_before_composes_sigkill(compose, name, variable):
    """SIGTERM drains for drain_grace_s (the compose file's, else the setting's default); compose
    SIGKILLs after stop_grace_period (default 10 s): the drain and uvicorn's shutdown must fit."""
    from service.settings import ServiceSettings
    from world_api.settings import WorldSettings

    settings = ServiceSettings if name == "service" else WorldSettings
    service = compose["services"][name]
    grace = float(service["environment"].get(variable, settings.model_fields["drain_grace_s"].default))
    stop = _seconds(service.get("stop_grace_period", "10s"))
    assert grace + 5 <= stop, f"{name}: drain {grace} s + 5 s of shutdown > stop_grace_period {stop} s"


def test_replicas_are_sim_workers_each_reached_by_name(compose):
    """Three workers behind one scoring service: each replica is the sim worker's service under its own name
    (a trial's calls must reach the worker holding its episode, so no `--scale` behind one DNS name), with no
    host port of its own; the replicas' planner lists every worker and starts when all are healthy."""
    services = compose["services"]
    workers = ["sim_worker", "sim_worker_2", "sim_worker_3"]
    for name in workers[1:]:
        replica = services[name]
        assert replica["profiles"] == ["replicas"] and replica["ports"] == []
        for key in ("image", "build", "environment", "healthcheck", "user", "stop_grace_period"):
            assert replica[key] == services["sim_worker"][key], (name, key)
    planner = services["planner_replicas"]
    assert planner["profiles"] == ["replicas"] and planner["command"] == services["planner"]["command"]
    port = _port(compose, "sim_worker")
    assert planner["environment"]["FIRP_PLANNER_SIM_URL"].split(",") == [f"http://{w}:{port}" for w in workers]
    assert planner["depends_on"] == {name: {"condition": "service_healthy"} for name in ["service", *workers]}

    from planner_client.session import ServicePlan

    assert ServicePlan(task="stacking", out_dir=ROOT, sim_url=planner["environment"]["FIRP_PLANNER_SIM_URL"],
                       service_url=planner["environment"]["FIRP_PLANNER_SERVICE_URL"]).sim_urls == \
        [f"http://{w}:{port}" for w in workers]  # how `firp run` reads the variable


def test_the_ray_profile_runs_a_collection_on_a_head_and_workers(compose):
    """ray_head starts the cluster's head without CPUs of its own and runs `firp collect --ray auto` on it
    (Ray's drivers run on a node of their cluster) with the command's arguments; ray_worker joins it by name."""
    head, worker = compose["services"]["ray_head"], compose["services"]["ray_worker"]
    assert head["profiles"] == worker["profiles"] == ["ray"]
    script = head["entrypoint"][2]
    assert head["entrypoint"][:2] == ["sh", "-c"]
    start, collect = script.split(" && exec ")
    assert start.startswith("ray start --head --port=6379 ") and "--num-cpus=0" in start
    assert collect == 'firp collect --ray auto "$$0" "$$@"'  # compose's $$ is the shell's $
    assert worker["entrypoint"] == ["ray"] and worker["command"][:2] == ["start", "--address=ray_head:6379"]
    assert "--block" in worker["command"]
    assert any(v.startswith("ray-data:/app/data") for v in head["volumes"])
    # the arguments are a valid `firp collect` command line
    from planner_client.__main__ import build_parser

    command = [re.sub(r"\$\{FIRP_\w+:-(\w+)\}", r"\1", str(a)) for a in head["command"]]
    args = build_parser("firp").parse_args(["collect", *command])
    assert args.out == Path("/app/data/stacking.h5") and (args.task, args.episodes, args.workers) == ("stacking", 640, 4)
    assert "ray==" in (ROOT / "pyproject.toml").read_text()


def test_build_contexts_leave_local_state_out():
    """Every build sends the context to the engine (podman unpacks a copy of it): the virtualenvs, datasets,
    runs and the smoke run's own image storage stay out, or a build costs gigabytes of disk it never uses."""
    ignored = {line.strip() for line in (ROOT / ".dockerignore").read_text().splitlines()
               if line.strip() and not line.startswith("#")}
    makefile = (ROOT / "Makefile").read_text()
    venvs = set(re.findall(r"^(?:RS_)?VENV \?= (\S+)$", makefile, re.M))
    assert venvs and venvs <= ignored, venvs - ignored
    assert {".git", "data", "runs", ".compose-smoke"} <= ignored
