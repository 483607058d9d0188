# weatheralign: `make reproduce` (set-up + whole pipeline) and `make test` (set-up + test suite).
SHELL := /bin/bash
PYTHON ?= python3.11
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
# The CPU build of torch: pip finds it where the machine keeps local wheels (or pass TORCH_PIP_ARGS, e.g. an index
# that serves +cpu wheels). A bare `torch` from the registry would pull several GB of CUDA packages.
TORCH_SPEC ?= torch==2.13.0
TORCH_PIP_ARGS ?=
STAMP := $(VENV)/.weatheralign-installed

export PREFECT_HOME := $(CURDIR)/.prefect
export PREFECT_SERVER_ANALYTICS_ENABLED := false
export PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS := 90
# the console shows warnings and errors; the flow and task runs' logs (INFO, prints included) still reach the
# Prefect API and its UI
export PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL ?= WARNING
export MLFLOW_TRACKING_URI ?= sqlite:///$(CURDIR)/mlflow.db
export OMP_NUM_THREADS ?= 2

.PHONY: setup reproduce browser test test-all lint bench prefect-ui serve mlflow-ui clean-venv

setup: $(STAMP)

$(STAMP): pyproject.toml Makefile
	@# open3d 0.20 imports only with libusb-1.0 present
	@if ! ldconfig -p | grep -q 'libusb-1.0.so.0'; then \
	  echo "[setup] installing Debian libusb-1.0-0 (needed by open3d)"; \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -qq && apt-get install -y -qq libusb-1.0-0; \
	  else sudo apt-get update -qq && sudo apt-get install -y -qq libusb-1.0-0; fi; \
	fi
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip setuptools wheel
	$(PIP) install -q $(TORCH_PIP_ARGS) "$(TORCH_SPEC)"
	$(PIP) install -q -e ".[pipeline,test]"
	$(PY) -c "import torch, open3d, nuscenes, prefect, mlflow; print('[setup] torch', torch.__version__, '| open3d', open3d.__version__, '| prefect', prefect.__version__, '| mlflow', mlflow.__version__)"
	@touch $(STAMP)

# one Prefect API server and one Dask cluster for every stage of the run (flows.api_server): they die with the run
reproduce: setup
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" WEATHERALIGN_PIPELINE_ID=repro-$$(date +%Y%m%d-%H%M%S) \
	  $(PY) -m flows.api_server --dask dvc repro

# the report's HTML page is checked in a real headless browser: Debian's chromium
browser:
	@if ! command -v chromium >/dev/null 2>&1; then \
	  echo "[test] installing Debian chromium (the report page's browser test)"; \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -qq && apt-get install -y -qq chromium >/dev/null; \
	  else sudo apt-get update -qq && sudo apt-get install -y -qq chromium >/dev/null; fi \
	  || echo "[test] chromium could not be installed: the browser test will be skipped"; \
	fi

# the fast tier: everything but the tests marked slow, on TEST_WORKERS processes (pytest-xdist; one file's tests stay
# on one worker, so a module's fixture is built once); TEST_WORKERS=0 runs them in this process
TEST_WORKERS ?= 2
test: setup browser lint
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile -m "not slow" $(PYTEST_ARGS)

# the fast tier and the end-to-end tier: whole stages through dvc repro / exp run, trainings, the pipeline flow
test-all: setup browser lint
	$(PY) -m pytest -q $(PYTEST_ARGS)

lint: setup
	$(VENV)/bin/ruff check src flows tasks tests benchmarks

bench: setup
	$(PY) -m benchmarks.bench_world

prefect-ui: setup
	$(VENV)/bin/prefect server start

# deployments of the pipeline and of every stage, run from the UI of `make prefect-ui` (flows/serve.py)
serve: setup
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" $(PY) -m flows.serve

mlflow-ui: setup
	$(VENV)/bin/mlflow ui --backend-store-uri "$(MLFLOW_TRACKING_URI)" --port 5000

clean-venv:
	rm -rf $(VENV)
