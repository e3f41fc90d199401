# esmm - the two commands a new user needs: `make demo` and `make test`.
SHELL   := /bin/bash
PYTHON  ?= python3
VENV    ?= .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.esmm-installed
DEMO_OUT ?= demo-output
BENCH_OUT ?= benchmarks/results.json
# The tested versions of every dependency (pip constraints). `make install LOCK=` installs
# the newest releases pyproject.toml allows instead; `make lock` refreshes the file.
LOCK    ?= requirements.lock
PIN     := $(if $(LOCK),-c $(LOCK),)

.DEFAULT_GOAL := help
.PHONY: help install check-system test test-fast demo bench bench-discover results lint lock clean

help: ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk 'BEGIN {FS = ":.*## "}; {printf "  make %-13s %s\n", $$1, $$2}'

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): pyproject.toml $(LOCK) | $(BIN)/python
	$(BIN)/python -m pip install --quiet $(PIN) -e '.[dev]'
	$(BIN)/python scripts/check_system.py
	@touch $@

install: $(STAMP) ## create .venv and install esmm with its dependencies

check-system: | $(BIN)/python ## check the system libraries gmsh and VTK need
	$(BIN)/python scripts/check_system.py

# The suite runs in TEST_JOBS worker processes (pytest-xdist; `auto`: one per core, at most 4):
# on two cores it takes about 0.6 of the serial time. `make test TEST_JOBS=0` runs it in one process.
TEST_JOBS ?= auto
XDIST   := $(if $(filter 0,$(TEST_JOBS)),-p no:xdist,-n $(TEST_JOBS) --maxprocesses 4)

test: install ## install and run the test suite
	$(BIN)/pytest -q $(XDIST)

test-fast: install ## the tests without the slow (meshing, rendering) ones
	$(BIN)/pytest -q $(XDIST) -m "not slow"

demo: install ## run the whole pipeline on the bundled real data (outputs in demo-output/)
	bash scripts/demo.sh "$(DEMO_OUT)"

bench: install ## run the benchmarks, write benchmarks/results.json, render benchmarks/RESULTS.md
	$(BIN)/python benchmarks/run.py --out "$(BENCH_OUT)"; status=$$?; \
	$(PYTHON) benchmarks/results_md.py && exit $$status

results: ## render benchmarks/RESULTS.md and the README's table from the committed JSON (no measuring)
	$(PYTHON) benchmarks/results_md.py

# The independent population (benchmarks/population): discovery's false-positive rate on clean
# cases and its confusion table; one `esmm calibrate --discover` per case, BENCH_JOBS at a time.
BENCH_CASES ?= 303
BENCH_SEED ?= 0
BENCH_JOBS ?= 2
BENCH_DISCOVER_OUT ?= benchmarks/population_results.json
bench-discover: install ## discovery on an independent population: 303 cases (200 clean, 103 with an effect), JSON in benchmarks/
	$(BIN)/python benchmarks/bench_discover_population.py --cases $(BENCH_CASES) --seed $(BENCH_SEED) \
		--jobs $(BENCH_JOBS) --clean-fraction 0.66 --timeout 300 --out "$(BENCH_DISCOVER_OUT)"

lock: ## refresh requirements.lock: the newest releases pyproject.toml allows, installed and frozen
	bash scripts/lock.sh "$(PYTHON)" requirements.lock

lint: install ## ruff
	$(BIN)/ruff check cli pipeline tests benchmarks scripts

clean: ## remove the virtual environment and outputs
	rm -rf $(VENV) $(DEMO_OUT) build *.egg-info .pytest_cache .ruff_cache
