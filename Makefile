# labkit — two commands on a fresh Debian machine:
#   make demo   install everything, then run the main job on the simulated rig
#   make test   install everything, then run the test suite
# `make bench` runs the benchmarks and the slow tests.
# `make docs` builds the documentation site into docs/_build/html (make test builds it too).
# `make lock` refreshes requirements.lock (uv pip compile), the pins that both install.

PYTHON   ?= python3
VENV     ?= .venv
PY       := $(VENV)/bin/python
DEB_PKGS := gir1.2-aravis-0.8 aravis-tools libgirepository1.0-dev libcairo2-dev pkg-config chromium
STAMP    := $(VENV)/.installed
DEMO_OUT ?= demo-out
BENCH_OUT?= bench-out
PYTEST_ARGS ?=
LOCK     := requirements.lock
UV       := uv==0.13.9
LOCK_FLAGS ?= --upgrade

.PHONY: demo test bench lint docs lock system-deps venv clean

demo: venv
	$(VENV)/bin/labkit demo --out $(DEMO_OUT)

# the docs first: a Sphinx warning fails the build, and tests/test_docs.py checks the site
test: lint docs
	$(VENV)/bin/pytest -m "not slow" $(PYTEST_ARGS)

# The documentation site (docs/): the user guide and the API tour, whose marked blocks run
# during the build (their output goes onto the pages), the example gallery, whose scripts
# run too, the API and command-line references, and the benchmarks page from the bench.json
# that `make bench` published. Warnings are errors; -E re-reads every page so that none is
# hidden by the cache (sphinx-gallery still skips examples whose script has not changed).
# Pages: docs/_build/html/index.html.
docs: venv
	$(VENV)/bin/sphinx-build -W --keep-going -E -b html docs docs/_build/html

# `bench all --full`: every stage, the full-size reconstruction and the whole 256²…2048²
# scaling sweep, then the slow tests. Its bench.json and plots are published into
# docs/benchmarks/, from which `make docs` builds the benchmarks page (commit them with the
# change they measure). The slow tests run even when a benchmark misses its target; make
# then fails.
bench: venv
	@status=0; \
	$(VENV)/bin/labkit bench all --full --out $(BENCH_OUT) || status=$$?; \
	if [ -f $(BENCH_OUT)/bench.json ]; then \
		rm -rf docs/benchmarks && mkdir -p docs/benchmarks && \
		cp $(BENCH_OUT)/bench.json $(BENCH_OUT)/*.png docs/benchmarks/; \
	fi; \
	$(VENV)/bin/pytest -m slow $(PYTEST_ARGS) || status=$$?; \
	exit $$status

# ruff, the layers of pyproject.toml's import contracts and mypy on the typed packages
# (docs/architecture.md)
lint: venv
	$(VENV)/bin/ruff check labkit calibration reconstruction tests
	$(VENV)/bin/ruff format --check labkit calibration reconstruction tests
	$(VENV)/bin/lint-imports --no-cache --no-logo
	$(VENV)/bin/mypy

# Debian packages from DESIGN.md: installed when missing (needs root, as in CI).
system-deps:
	@missing=""; for p in $(DEB_PKGS); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:$$missing"; \
	  if [ "$$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing \
	    || { echo "error: could not install$$missing; install them with apt-get (as root) and retry" >&2; exit 1; }; \
	fi

venv: $(STAMP)

# The package's own dependencies are ranges (pyproject.toml); what is installed here is
# pinned by the lock, so that every machine tests the same versions.
$(STAMP): pyproject.toml $(LOCK) | system-deps
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c $(LOCK) -e ".[gige,genicam,xarray,bluesky,tiled,docs,dev]"
	@touch $(STAMP)

# Newest versions within pyproject.toml's ranges, for every platform and Python ≥ 3.11
# (`make lock LOCK_FLAGS=` keeps the current pins and only adds what is new).
lock:
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet "$(UV)"
	$(VENV)/bin/uv pip compile pyproject.toml --extra gige --extra genicam --extra xarray --extra bluesky --extra tiled --extra docs --extra dev \
	  --universal --python-version 3.11 --custom-compile-command "make lock" \
	  --quiet $(LOCK_FLAGS) -o $(LOCK)

clean:
	rm -rf $(VENV) $(DEMO_OUT) $(BENCH_OUT) .pytest_cache .ruff_cache
	rm -rf docs/_build docs/api docs/auto_examples docs/sg_execution_times.rst
