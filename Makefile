# gpc: every target sets up its own virtual environment from the project's files first.
PYTHON ?= python3
VENV ?= .venv
PROFILE ?= cpu
BIN := $(VENV)/bin
STAMP := $(VENV)/.gpc-installed
# The CPU build of torch; a plain `torch` requirement could pull a multi-GB CUDA build.
TORCH_SPEC ?= torch==2.13.0
WORKERS ?= 2
RUN_DIR ?= runs/pusht-$(PROFILE)
RESULTS ?= results/pusht-$(PROFILE)

# Profiles: smoke (minutes, used by tests), cpu (default, 2 cores), paper (paper sizes, GPU).
ifeq ($(PROFILE),smoke)
  EXPERT_EPISODES := 4
  EXPLORE_EPISODES := 4
  POLICY := --profile tiny --max-steps 40
  EVAL := --seeds 100000:100004 --max-steps 40 --batch 4
else ifeq ($(PROFILE),paper)
  EXPERT_EPISODES := 1000
  EXPLORE_EPISODES := 1000
  POLICY := --profile paper
  EVAL := --seeds 100000:100100 --batch 50
else ifeq ($(PROFILE),cpu)
  EXPERT_EPISODES := 200
  EXPLORE_EPISODES := 200
  POLICY := --profile cpu
  EVAL := --seeds 100000:100050 --batch 25
else
  $(error PROFILE=$(PROFILE): use smoke, cpu or paper)
endif

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

# Each stage resumes: re-running skips the episodes already collected.
reproduce-pusht: $(STAMP)
	$(BIN)/gpc collect --out $(RUN_DIR)/expert.zarr --episodes $(EXPERT_EPISODES) --seed 0 --workers $(WORKERS)
	$(BIN)/gpc collect --explore --out $(RUN_DIR)/explore.zarr --episodes $(EXPLORE_EPISODES) --seed 50000 --workers $(WORKERS)
	$(BIN)/gpc data info $(RUN_DIR)/expert.zarr
	$(BIN)/gpc data info $(RUN_DIR)/explore.zarr
	test -f $(RUN_DIR)/policy/done || { \
	  if [ -f $(RUN_DIR)/policy/checkpoints/last.ckpt ]; then resume=--resume; fi; \
	  $(BIN)/gpc train policy --dataset $(RUN_DIR)/expert.zarr --obs keypoints $(POLICY) --seed 0 \
	    --out $(RUN_DIR)/policy $$resume && touch $(RUN_DIR)/policy/done; }
	test -f $(RESULTS)/bc/summary.md || $(BIN)/gpc eval $(RUN_DIR)/policy/checkpoints/last.ckpt \
	  $(EVAL) --workers $(WORKERS) --out $(RESULTS)/bc
	@echo "Stages to come (open issues): train the world model (phase 1, 2) and the rewards, evaluate"
	@echo "GPC-RANK, GPC-OPT, GPC-RANK+OPT and the baselines next to BC into results/pusht_state.md."

clean:
	rm -rf $(VENV) runs results .pytest_cache
