# One-command set-up and runs. Every target creates .venv on first use; nothing is installed system-wide.
# torch (CPU build) is installed before stable-baselines3 so pip never pulls the multi-GB CUDA build.

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
PY     := $(BIN)/python

export NUMBA_CACHE_DIR ?= $(CURDIR)/.numba_cache
export NUMBA_NUM_THREADS ?= 2
export OMP_NUM_THREADS ?= 2
# MkDocs plugins print a banner about MkDocs 2 on every build; these silence it.
export DISABLE_MKDOCS_2_WARNING ?= true
export NO_MKDOCS_2_WARNING ?= 1

.PHONY: setup setup-train run demo test validate bench lint docs clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

# Core package + test/render/viewer/docs extras. Re-run when pyproject.toml changes.
$(VENV)/.core: pyproject.toml | $(PY)
	$(PY) -m pip install --quiet -e ".[dev,render,viewer,docs]"
	touch $@

# RL extras: CPU torch first, then SB3 and friends.
$(VENV)/.train: pyproject.toml $(VENV)/.core
	$(PY) -m pip install --quiet "torch==2.13.0"
	$(PY) -m pip install --quiet -e ".[train]"
	touch $@

setup: $(VENV)/.core

setup-train: $(VENV)/.train

## The main job (README quick start, command 1): train DAgger on NeedleInsert (~8 min on 2 cores) with a
## progress bar, evaluate it beside the committed models, write runs/dagger_NeedleInsert_s0/{learning_curve.png,policy.mp4}.
run: setup-train
	$(PY) scripts/main_job.py

## The tissue demo (the previous main job).
demo: setup
	$(PY) scripts/demo_tissue.py

## The test suite (README quick start, command 2; CI runs exactly this). Includes the RL extras so the
## SB3 pipeline and check_env tests run.
test: setup-train
	$(PY) -m pytest -q

validate: setup
	$(PY) scripts/validate_physics.py

bench: setup
	$(PY) scripts/bench.py

## The documentation site (MkDocs, warnings as errors) -> site/.
docs: setup
	$(BIN)/mkdocs build --strict

lint: setup
	$(BIN)/ruff check suture_gym scripts tests

clean:
	rm -rf $(VENV) .numba_cache .pytest_cache .ruff_cache out site
