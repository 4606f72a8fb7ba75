# pemamoe: every entry point of the project. `make help` lists them.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# torch==2.13.0+cpu is not on PyPI: when the lock does not resolve from the configured indexes, the
# install is retried with PyTorch's CPU wheel index (a mirror can be named: make TORCH_INDEX=...).
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
SCALE ?= medium
BACKEND ?= local
WORKERS ?= 2
PYTEST_ARGS ?= -n 2
RETRAIN ?=
RESULTS ?= results
RAY_ADDRESS ?=
LAB_ARGS ?=

.PHONY: help test figures export check-export lab bench clean lock venv

help:
	@echo "make test                  build .venv from environment.lock if needed, run the whole suite"
	@echo "make figures [SCALE=ci|small|medium|paper] [RETRAIN=1] [RESULTS=s3://...] [BACKEND=ray RAY_ADDRESS=auto]  regenerate paper_figures/ from the run records (RETRAIN=1: retrain them; RESULTS: the results store; RAY_ADDRESS: a Ray cluster)"
	@echo "make export | check-export notebooks -> pemamoe/ | fail if pemamoe/ differs from the notebooks"
	@echo "make lab [LAB_ARGS=...]    JupyterLab, with notebooks/*.py opening as notebooks (LAB_ARGS: options for jupyter lab, e.g. --ip, --port, --IdentityProvider.token)"
	@echo "make bench                 print the performance figures (peers included: installs the extra bench) and write them to benchmarks/RESULTS.md"
	@echo "make lock                  regenerate environment.lock from requirements.in"
	@echo "make clean                 remove build/, the test caches and __pycache__ folders (keeps .venv, results/, records/, paper_figures/)"

# The environment is rebuilt from scratch whenever the lock or the package metadata is newer than
# the last install, so .venv never drifts from environment.lock.
$(STAMP): environment.lock pyproject.toml
	rm -rf $(VENV)
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r environment.lock || { echo "[venv] retrying with PyTorch's CPU wheel index ($(TORCH_INDEX)) for torch==2.13.0+cpu"; $(PY) -m pip install --quiet --extra-index-url $(TORCH_INDEX) -r environment.lock; }
	$(PY) -m pip install --quiet --no-deps --no-build-isolation -e .
	@touch $@

venv: $(STAMP)

test: $(STAMP)
	$(PY) -m pemamoe.literate check
	$(PY) -c "from pemamoe.env import compile_step_kernels; compile_step_kernels()"  # once, before the parallel workers
	$(PY) -m pytest $(PYTEST_ARGS)

# Prints "[figures] i/N notebook ... elapsed" lines and streams each notebook's own output. The
# kernels' "Kernel is running over TCP without encryption" warnings are fixed at their cause, not
# filtered: the runner provisions CurveZMQ keys (transport_encryption="auto"; notebooks/00b_core.py).
figures: $(STAMP)
	$(PY) -m pemamoe figures --scale $(SCALE) --backend $(BACKEND) --workers $(WORKERS) --results-dir $(RESULTS) $(if $(RETRAIN),--retrain,) $(if $(RAY_ADDRESS),--ray-address $(RAY_ADDRESS),)

export: $(STAMP)
	$(PY) -m pemamoe.literate export

check-export: $(STAMP)
	$(PY) -m pemamoe.literate check

# Project-local JupyterLab settings: .py files open in the Jupytext notebook view by default.
# jupytext.toml (repo root) keeps the committed headers as they are, so opening and autosaving an
# unchanged notebook changes nothing, and pairs each notebook with build/notebooks/NN_*.ipynb
# (gitignored), where its outputs survive between sessions. The .py stays the source.
lab: $(STAMP)
	@mkdir -p $(VENV)/share/jupyter/lab/settings
	@echo '{"@jupyterlab/docmanager-extension:plugin": {"defaultViewers": {"python": "Jupytext Notebook"}}}' \
		> $(VENV)/share/jupyter/lab/settings/overrides.json
	$(VENV)/bin/jupyter lab --ServerApp.root_dir=. $(if $(filter 0,$(shell id -u)),--allow-root,) $(LAB_ARGS)

# The peers of bench_peers.py come with the extra `bench`, installed once into .venv beside the lock.
BENCH_STAMP := $(VENV)/.bench-installed
$(BENCH_STAMP): $(STAMP) pyproject.toml
	$(PY) -m pip install --quiet --no-build-isolation -e ".[bench]"
	@touch $@

bench: $(BENCH_STAMP)
	$(PY) benchmarks/run.py

lock:
	TORCH_INDEX=$(TORCH_INDEX) bash tools/lock.sh $(PYTHON)

clean:
	rm -rf build .pytest_cache .hypothesis
	find . -name __pycache__ -type d -not -path './$(VENV)/*' -prune -exec rm -rf {} +
