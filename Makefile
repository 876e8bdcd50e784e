# Two commands, each sets everything up from nothing (idempotently) first:
#   make demo   - the whole stack on the built-in synthetic building, on loopback
#   make test   - the test suite
#   make compose-test - builds the image, runs docker-compose.yml on the host network and checks
#                  it (needs a Docker engine; not part of make test; ARGS=--tls, ARGS=--scaled)
#   make mutation - breaks the product in named ways, one at a time in a copy of the tree, and
#                  checks the tests catch each (minutes; not part of make test; docs/testing.md)
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.aisdf-installed

.PHONY: setup demo test compose-test mutation bench-query bench-scaling bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dev]"
	@# open3d (baseline, mesh ray casting) needs libusb at import; install it where apt-get can.
	$(PY) -c "import open3d" 2>/dev/null || { command -v apt-get >/dev/null && \
	  { apt-get install -y -qq libusb-1.0-0 >/dev/null 2>&1 || { apt-get update -qq && apt-get install -y -qq libusb-1.0-0; }; }; }
	$(PY) -c "import open3d" || { echo "open3d does not import: install libusb-1.0-0 (Debian/Ubuntu)"; exit 1; }
	touch $(STAMP)

demo: setup
	$(VENV)/bin/aisdf demo $(ARGS)

test: setup
	$(VENV)/bin/pytest -q --durations=12 $(ARGS)

compose-test: setup
	$(PY) tests/run_compose_test.py $(ARGS)

mutation: setup
	$(PY) tests/run_mutation_check.py $(ARGS)

bench-query: setup
	$(VENV)/bin/aisdf bench query $(ARGS)

bench-scaling: setup
	$(VENV)/bin/aisdf bench scaling $(ARGS)

bench: setup
	$(VENV)/bin/aisdf bench $(ARGS)

clean:
	rm -rf $(VENV) runs results .pytest_cache
