# The two commands a new user runs: `make demo` and `make test`. Both create .venv if missing.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.ntp-installed
WEB    := ntp_engine/pipeline/web
BUNDLE := $(WEB)/dist/viewer.js
NPM_PACKAGES := three@0.187.0 esbuild@0.28.2 playwright-core@1.65.1 gltf-validator@2.0.0-dev.3.10

.PHONY: demo test test-fast lint setup bench extension clean

$(STAMP): requirements.txt pyproject.toml Makefile
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -c 'import sys; assert sys.version_info[:2] == (3, 11), "ntp needs Python 3.11 (bpy 5.0.1); set PYTHON=python3.11"'
	$(BIN)/python -m pip install -q --upgrade pip
	# torch first and pinned, so nothing else can pull the CUDA build
	$(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -r requirements.txt
	$(BIN)/python -m pip install -q --no-deps -e .
	# the engine's numba loops compiled into their cache now, not in the first run (~20 s)
	$(BIN)/python -m ntp_engine.pipeline.precompile
	# where node/npm exist (pinned): the Khronos glTF validator for the add-on's tests; three.js and
	# esbuild for the result page's 3D view; playwright-core to drive Chromium in the browser check
	if command -v npm >/dev/null; then npm install --silent --no-audit --no-fund --save-exact --prefix $(VENV)/node $(NPM_PACKAGES); fi
	# Debian's Chromium for the browser check (tests/bench/test_browser.py), where apt exists and we may use it
	if [ ! -x /usr/bin/chromium ] && command -v apt-get >/dev/null && [ "$$(id -u)" = 0 ]; then \
		{ DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null 2>&1 || \
		  { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null; }; } || \
		echo "chromium not installed: the browser check will be skipped"; fi
	touch $(STAMP)

# the result page's script with three.js bundled in (ntp_engine/pipeline/result_page.py), where npm exists
$(BUNDLE): $(WEB)/viewer.js $(STAMP)
	if [ -x $(VENV)/node/node_modules/.bin/esbuild ]; then \
		NODE_PATH=$(VENV)/node/node_modules $(VENV)/node/node_modules/.bin/esbuild $(WEB)/viewer.js --bundle \
			--format=iife --minify --log-level=warning --outfile=$(BUNDLE); fi

setup: $(STAMP) $(BUNDLE)

demo: setup
	$(BIN)/ntp demo

# one test process per core (pytest-xdist), each on one thread: torch's, BLAS's and numba's own
# threads in two processes on 2 cores fought (the suite took longer than in one process); one
# thread each: 12:40 against 20:16 in one process (2 cores, 2026-12-02; docs/architecture.md)
ONE_THREAD := OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 NUMBA_NUM_THREADS=1
test: setup
	$(ONE_THREAD) $(BIN)/python -m pytest -q -n auto --durations=20

# the fast tier: everything but SfM, Cycles, Ray and whole-pipeline runs (tests/conftest.py marks those slow)
test-fast: setup
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
