# The two commands a new user runs: `make demo` and `make test`. Both create .venv if missing.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.ntp-installed

.PHONY: demo test test-fast lint setup bench extension clean

$(STAMP): requirements.txt pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -c 'import sys; assert sys.version_info[:2] == (3, 11), "ntp needs Python 3.11 (bpy 5.0.1); set PYTHON=python3.11"'
	$(BIN)/python -m pip install -q --upgrade pip
	# torch first and pinned, so nothing else can pull the CUDA build
	$(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -r requirements.txt
	$(BIN)/python -m pip install -q --no-deps -e .
	# the engine's numba loops compiled into their cache now, not in the first run (~20 s)
	$(BIN)/python -m ntp_engine.pipeline.precompile
	# the Khronos glTF validator for the add-on's tests, where node/npm exist (pinned)
	if command -v npm >/dev/null; then npm install --silent --no-audit --no-fund --prefix $(VENV)/node gltf-validator@2.0.0-dev.3.10; fi
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/ntp demo

# one test process per core (pytest-xdist), each on one thread: torch's, BLAS's and numba's own
# threads in two processes on 2 cores fought (the suite took longer than in one process); one
# thread each: 12:40 against 20:16 in one process (2 cores, 2026-12-02; docs/architecture.md)
ONE_THREAD := OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 NUMBA_NUM_THREADS=1
test: $(STAMP)
	$(ONE_THREAD) $(BIN)/python -m pytest -q -n auto --durations=20

# the fast tier: everything but SfM, Cycles, Ray and whole-pipeline runs (tests/conftest.py marks those slow)
test-fast: $(STAMP)
	$(ONE_THREAD) $(BIN)/python -m pytest -q -n auto -m "not slow"

# lint (ruff), format check (ruff format) and types (mypy, settings in pyproject.toml); CI runs it
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

bench: $(STAMP)
	$(BIN)/ntp bench physics
	$(BIN)/ntp bench stability

extension: $(STAMP)
	$(BIN)/python tools/build_extension.py --out dist

clean:
	rm -rf $(VENV) ntp_demo_out ntp_gallery .pytest_cache .hypothesis build dist
