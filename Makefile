# Two entry points for a fresh machine with only Python 3.11 and make:
#   make run    a simulated flight with everything on (the main job)
#   make test   the test suite
# Both create .venv from pyproject.toml when it is missing or older than pyproject.toml.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

# Peer programs beside the checkout (a real ArduPlane SITL, mavlink-router): their absolute paths
# go to the tests and benchmarks when the files exist there; a value from the environment wins.
# Without them the tests that need them are deselected, with one line saying how many and why.
ARDUPILOT_SITL ?= $(abspath $(wildcard ../shared/tools/ardupilot/arduplane))
MAVLINK_ROUTER ?= $(abspath $(wildcard ../shared/tools/mavlink-router/mavlink-routerd))
ifneq ($(ARDUPILOT_SITL),)
export ARDUPILOT_SITL
endif
ifneq ($(MAVLINK_ROUTER),)
export MAVLINK_ROUTER
endif

.PHONY: run test test-peers test-cluster lint bench bench-quick bench-faults bench-soak docs clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/companion sim --duration 120 --scenario mixed --realtime --horizon-camera thesis

# Two pytest-xdist workers, a test file each at a time: on the 2-core development machine the
# suite takes about 6.5 minutes instead of about 18 (the real-time tests hold beside another
# worker as they must beside any other load).
test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile -m "not sitl and not router and not cluster"

# The tests against the peer programs (the real ArduPlane SITL, mavlink-routerd): a few minutes
# more, so apart from `make test`; .ci/run runs both. Without the programs pytest deselects
# them all and says so (exit 5: no test ran, which is not a failure here).
test-peers: $(STAMP)
	$(BIN)/python -m pytest -q -m "sitl or router" || [ $$? -eq 5 ]

# Campaigns on a real two-node Ray cluster in a loopback-only network namespace (about a minute
# and a half; needs root or user namespaces for `unshare -n`): apart from `make test`, .ci/run
# runs it.
test-cluster: $(STAMP)
	$(BIN)/python -m pytest -q -m cluster

lint: $(STAMP)
	$(BIN)/ruff check companion gcs_bridge horizon legacy_protocol tests bench
	$(BIN)/mypy companion gcs_bridge horizon legacy_protocol

bench: $(STAMP)
	$(BIN)/python bench/run_all.py

bench-quick: $(STAMP)
	$(BIN)/python bench/run_all.py --quick

bench-faults: $(STAMP)
	$(BIN)/python bench/faults_bench.py
	$(BIN)/python bench/fuzz_bench.py

bench-soak: $(STAMP)
	$(BIN)/python bench/soak_bench.py

docs: $(STAMP)
	$(BIN)/python -m companion.docgen docs/parameters.md
	$(BIN)/python bench/render.py docs/benchmarks.md

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
