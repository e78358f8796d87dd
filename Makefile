# gpc: every target sets up its own virtual environment from the project's files first.
PYTHON ?= python3
VENV ?= .venv
PROFILE ?= cpu
BIN := $(VENV)/bin
STAMP := $(VENV)/.gpc-installed
# The CPU build of torch; a plain `torch` requirement could pull a multi-GB CUDA build.
TORCH_SPEC ?= torch==2.13.0

.PHONY: help venv test bench reproduce-pusht check-sim clean

help:
	@echo "make reproduce-pusht   collect data and run the Push-T pipeline (PROFILE=cpu|smoke|paper)"
	@echo "make test              run the test suite"
	@echo "make bench             run the benchmarks and append their figures to README.md"
	@echo "make check-sim         replay and render the shared human data through our simulator"

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q "$(TORCH_SPEC)"
	$(BIN)/python -m pip install -q -e ".[dev]"
	touch $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python benchmarks/run_all.py --readme README.md

check-sim: $(STAMP)
	$(BIN)/gpc check-sim

reproduce-pusht: $(STAMP)
	PROFILE=$(PROFILE) $(BIN)/python -m gpc_cli.reproduce pusht

clean:
	rm -rf $(VENV) runs results .pytest_cache
