# Two entry points for a fresh machine with only Python 3.11 and make:
#   make run    a simulated flight with everything on (the main job)
#   make test   the test suite
# Both create .venv from pyproject.toml when it is missing or older than pyproject.toml.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: run test lint bench bench-quick bench-faults bench-soak docs clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/companion sim --duration 120 --scenario mixed --realtime --horizon-camera thesis

test: $(STAMP)
	$(BIN)/python -m pytest -q

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

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
