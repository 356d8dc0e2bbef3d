# Two commands on a fresh machine: `make run` (the main job) and `make test` (the test suite).
# Both create .venv when it is missing and install the project with the pinned stack; a second run
# reinstalls nothing unless setup.cfg, pyproject.toml or constraints.txt changed.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
EXTRAS ?= recipes,test,dev,docs,loggers
export MUJOCO_GL ?= egl
export PYTHONUNBUFFERED := 1

# test processes for the suite (pytest-xdist; each test file runs whole in one of them)
TEST_WORKERS ?= auto

SEEDS  ?= 0,1,2,3,4
PROFILE ?= default
SEEDS_DIR ?= outputs/pusher_competency/seeds$(if $(filter-out default,$(PROFILE)),_$(PROFILE))

.PHONY: run run-quick run-seeds demo test test-slow test-all lint format docs bench system-deps setup clean

run: setup
	$(PY) recipes/pusher_competency/main.py profile=$(PROFILE)

run-quick: setup
	$(PY) recipes/pusher_competency/main.py profile=quick

# The study for every seed of SEEDS (Hydra multirun) in PROFILE, then one table over them
# (e.g. `make run-seeds PROFILE=action_noise`: written under outputs/pusher_competency/seeds_action_noise).
run-seeds: setup
	$(PY) recipes/pusher_competency/main.py -m hydra/launcher=local seed=$(SEEDS) threads=1 stage_workers=1 \
		profile=$(PROFILE) progress=false \
		'run_dir=$(SEEDS_DIR)/seed$${seed}'
	$(PY) recipes/pusher_competency/aggregate.py $(SEEDS_DIR)

demo: setup
	$(PY) recipes/pusher_demo.py

test: setup
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile

test-slow: setup
	$(PY) -m pytest -q -m slow -n $(TEST_WORKERS) --dist loadfile

test-all: setup
	$(PY) -m pytest -q -m "slow or not slow" -n $(TEST_WORKERS) --dist loadfile

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: setup
	$(VENV)/bin/ruff check --fix .
	$(VENV)/bin/ruff format .

docs: setup
	$(VENV)/bin/sphinx-build -W --keep-going -b html docs docs/_build/html

bench: setup
	$(PY) benchmarks/env_speed.py
	$(PY) benchmarks/batched_backends.py
	$(PY) benchmarks/competency.py
	$(PY) benchmarks/imagination.py
	$(PY) benchmarks/world_model_speed.py
	$(PY) benchmarks/world_model.py
	$(PY) benchmarks/planning.py

setup: system-deps $(STAMP)

$(PY):
	$(PYTHON) -m venv $(VENV)

$(STAMP): setup.cfg pyproject.toml constraints.txt | $(PY)
	$(PY) -m pip install --quiet --disable-pip-version-check -c constraints.txt -e ".[$(EXTRAS)]"
	touch $(STAMP)

# Offscreen MuJoCo rendering needs an EGL library (Mesa). Installed only when it is missing.
system-deps:
	@if ! ldconfig -p 2>/dev/null | grep -q 'libEGL.so.1'; then \
		if command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
			echo "installing EGL (Mesa) for offscreen rendering"; \
			apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
				libegl1 libegl-mesa0 libgl1 libgles2 >/dev/null; \
		else \
			echo "warning: no libEGL and no root apt-get: rendering tests will be skipped"; \
		fi; \
	fi
	@if ! command -v g++ >/dev/null 2>&1; then \
		if command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
			echo "installing g++ (torch.compile's CPU kernels)"; \
			apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq g++ >/dev/null; \
		else \
			echo "warning: no g++ and no root apt-get: the compiled-scoring test will fail"; \
		fi; \
	fi

clean:
	rm -rf $(VENV) docs/_build .pytest_cache .ruff_cache
