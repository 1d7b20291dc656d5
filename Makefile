# firp: one entry point for developers and CI. `make test` on a fresh machine installs everything
# (system GL libraries for headless MuJoCo rendering, then a virtualenv with all extras) and runs
# the test suite; a second `make test` reuses the install (stamp files) unless pyproject.toml changed.

PYTHON ?= python3
VENV ?= .venv
VENV_PY := $(VENV)/bin/python
PIP_STAMP := $(VENV)/.installed-dev.stamp
# The robosuite world's own environment (robosuite pins another MuJoCo and numpy < 2).
RS_VENV ?= .venv-robosuite
RS_STAMP := $(RS_VENV)/.installed.stamp
APT_STAMP := .make/apt-deps.stamp
# Headless rendering: EGL by default; `MUJOCO_GL=osmesa make test` overrides it.
MUJOCO_GL ?= egl
export MUJOCO_GL
TRIALS ?= 50
PYTEST_ARGS ?=

# EGL/OSMesa runtime libraries MuJoCo's renderer loads by name (libEGL.so.1, libOSMesa.so.*),
# docker-compose (v1), which validates docker-compose.yml without a Docker engine (tests/test_compose.py),
# and PostgreSQL's server, which the tests start for Optuna studies shared by several workers.
APT_PACKAGES := libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0 libosmesa6 docker-compose postgresql

.PHONY: install robosuite-install system-deps test test-fast test-main test-robosuite run compose-smoke docs clean

install: $(PIP_STAMP)

system-deps: $(APT_STAMP)

# apt only where it can work (Debian-like machine, running as root); elsewhere say what is needed
# and go on, since a developer's machine may already have the libraries.
$(APT_STAMP):
	@mkdir -p $(dir $@)
	@if command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = "0" ]; then \
		echo ">> apt-get install $(APT_PACKAGES)"; \
		apt-get update && \
		DEBIAN_FRONTEND=noninteractive apt-get install -y $(APT_PACKAGES); \
	else \
		echo ">> skipping apt (no apt-get or not root); make sure these are installed: $(APT_PACKAGES)"; \
	fi
	@touch $@

# The venv stamp depends on pyproject.toml: changing dependencies reinstalls, nothing else does
# (the apt stamp is order-only: redoing apt must not force a pip reinstall).
$(PIP_STAMP): pyproject.toml | $(APT_STAMP)
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install -e ".[dev]"
	@touch $@

$(RS_STAMP): pyproject.toml | $(APT_STAMP)
	$(PYTHON) -m venv $(RS_VENV)
	$(RS_VENV)/bin/pip install -e ".[robosuite-dev]"
	@touch $@

robosuite-install: $(RS_STAMP)

# Both worlds' suites: the main environment's, then the robosuite world's in its own environment.
test: test-main test-robosuite

test-main: install
	MUJOCO_GL=$(MUJOCO_GL) $(VENV_PY) -m pytest -q --ignore=tests/robosuite_worker $(PYTEST_ARGS)

# The edit loop: every package's tests but the slow and golden ones (markers in pyproject.toml); the
# robosuite world's too where its environment was made (`make robosuite-install`). `make test` stays
# the whole suite and what CI runs.
FAST := -m "not slow and not golden"
test-fast: install
	MUJOCO_GL=$(MUJOCO_GL) $(VENV_PY) -m pytest -q --ignore=tests/robosuite_worker $(FAST) $(PYTEST_ARGS)
	@if [ -x $(RS_VENV)/bin/python ]; then \
		MUJOCO_GL=$(MUJOCO_GL) PYOPENGL_PLATFORM=$(MUJOCO_GL) $(RS_VENV)/bin/python -m pytest -q tests/robosuite_worker $(FAST) $(PYTEST_ARGS); \
	else echo ">> tests/robosuite_worker skipped: no $(RS_VENV) (make robosuite-install makes it)"; fi

test-robosuite: robosuite-install
	MUJOCO_GL=$(MUJOCO_GL) PYOPENGL_PLATFORM=$(MUJOCO_GL) $(RS_VENV)/bin/python -m pytest -q tests/robosuite_worker $(PYTEST_ARGS)

run: install
	MUJOCO_GL=$(MUJOCO_GL) $(VENV)/bin/firp run --trials $(TRIALS)

# docker-compose.yml for real: build the three images, run the main job's first trials in containers
# and compare their scores with the same trials run without them (podman here, Docker where one runs).
compose-smoke: install
	bash scripts/compose_smoke.sh

# The documentation site (MkDocs, offline): docs/*.md -> site/; --strict fails on a broken link.
docs: install
	$(VENV)/bin/mkdocs build --strict --site-dir site

clean:
	rm -rf $(VENV) $(RS_VENV) .make .pytest_cache *.egg-info site .compose-smoke
	find . -path ./.git -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +
