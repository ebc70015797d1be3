# eha_ros: build, install and test in a local virtual environment (.venv).
#
#   make demo    install, then run the main job: the test campaign through the ROS graph
#   make test    install (with requirements-bench.txt: the suite runs every bench in smoke
#                mode), the Foxglove test client (npm ci; Node >= 18), lint (flake8), then
#                run the test suite against the installed package
#   make install create .venv, install requirements.txt and the package (non-editable)
#   make bench   install, plus requirements-bench.txt, then run the benchmarks
#   make clean   remove .venv and build outputs
#
# The package is always installed with `pip install .` (not editable): the ROS 2 message
# classes and libraries are generated at build time and exist only in the installed copy.

PYTHON ?= python3
VENV ?= .venv
PYTEST_ARGS ?=
# pytest-xdist workers of `make test` (every test that starts nodes has its own ROS domain)
TEST_WORKERS ?= 2
BENCH ?= bench/plant_rtf.py
BENCH_ARGS ?=

# The Node client the live-view tests drive (Foxglove's own libraries, pinned by its lock file).
NODE_CLIENT := test/foxglove_client
NPM ?= npm

BIN := $(VENV)/bin
STAMPS := $(VENV)/.stamps
PIP := $(BIN)/pip --disable-pip-version-check
# Everything the installed package is built from (folders too: a deleted file changes them).
PACKAGE_SOURCES := setup.py setup.cfg pyproject.toml package.xml MANIFEST.in \
	$(shell find eha_ros msg rosidl_build config resource -not -path '*/__pycache__*' \
		-not -name '*.pyc' 2>/dev/null)

.PHONY: all install node-client demo test lint bench clean

all: test

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(STAMPS)/requirements: requirements.txt setup.py | $(BIN)/python
	$(PIP) install -r requirements.txt
	@mkdir -p $(STAMPS) && touch $@

$(STAMPS)/requirements-bench: requirements-bench.txt requirements.txt | $(BIN)/python
	$(PIP) install -r requirements-bench.txt
	@mkdir -p $(STAMPS) && touch $@

# (a changed package drops its own numba disk cache when imported: eha_ros.jit_cache)
$(STAMPS)/package: $(STAMPS)/requirements $(PACKAGE_SOURCES)
	$(PIP) install --no-deps --force-reinstall .
	@mkdir -p $(STAMPS) && touch $@

install: $(STAMPS)/package

# npm ci writes node_modules/.package-lock.json: newer than the lock file once installed.
$(NODE_CLIENT)/node_modules/.package-lock.json: $(NODE_CLIENT)/package-lock.json $(NODE_CLIENT)/package.json
	cd $(NODE_CLIENT) && $(NPM) ci --no-audit --no-fund

node-client: $(NODE_CLIENT)/node_modules/.package-lock.json

# .venv/bin/pytest (not `python -m pytest`, which would put the source folder on sys.path):
# the tests import the installed eha_ros, which carries the generated eha_ros.msg.
test: install $(STAMPS)/requirements-bench node-client lint
	$(BIN)/pytest -n $(TEST_WORKERS) --dist worksteal $(PYTEST_ARGS)

# flake8 (configured in setup.cfg) over the package, the tests, the benches and the build.
lint: $(STAMPS)/requirements
	$(BIN)/flake8 eha_ros test bench rosidl_build setup.py

# The main job: the reference's test campaign (steps, ramps, sines x hf, ga, nn, lut) through
# the ROS 2 graph in lockstep, every run recorded to MCAP, then a report (runs/campaign-*/).
demo: install
	$(BIN)/eha-campaign

bench: install $(STAMPS)/requirements-bench node-client
	$(BIN)/python $(BENCH) $(BENCH_ARGS)

clean:
	rm -rf $(VENV) build dist *.egg-info .pytest_cache $(NODE_CLIENT)/node_modules
	find . -path ./.git -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +
