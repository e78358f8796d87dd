# gpc: every target sets up its own virtual environment from the project's files first.
PYTHON ?= python3
VENV ?= .venv
PROFILE ?= cpu
BIN := $(VENV)/bin
STAMP := $(VENV)/.gpc-installed
# The CPU build of torch; a plain `torch` requirement could pull a multi-GB CUDA build.
TORCH_SPEC ?= torch==2.13.0
WORKERS ?= 2
# BACKEND=ray: the collect, record and eval stages run on Ray (RAY_ADDRESS=HOST:PORT: a running cluster; default: one
# started per command on this machine); the results are the local backend's (docs/scale-out.md).
BACKEND ?= local
RAY_ADDRESS ?=
SCALE := --backend $(BACKEND)$(if $(RAY_ADDRESS), --ray-address $(RAY_ADDRESS))
# make test: pytest processes, one torch thread each (the suite is mostly single-threaded subprocesses).
TEST_WORKERS ?= 2
# TASK: the task a pipeline runs (pusht, swap, draw, or one of yours named in GPC_TASKS); its runs and results folders are its own.
TASK ?= pusht
RUN_DIR ?= runs/$(TASK)-$(PROFILE)
# Per task: the state policy's observations, its name in table titles and the paper's state table (if it has one).
POLICY_OBS.pusht := keypoints
TITLE.pusht := Push-T
TITLE.swap := Cube & Sphere Swapping
TITLE.draw := Triangle Drawing
TITLE.stack := Block Stacking
PAPER_STATE.pusht := --paper pusht-state
# Swap's three-phase demonstrations at PROFILE=cpu: 400 (its state policy overfit 200: validation loss rising from step 2,200 of 3,000).
CPU_EXPERT_EPISODES.swap := 400
# Per task, vision: the paper's vision row (`gpc compare --paper`, the task's PAPER) where it has one.
PAPER_VISION.pusht := --paper pusht-vision
PAPER_VISION.swap := --paper swap-vision
PAPER_VISION.draw := --paper draw-vision
PAPER_VISION.stack := --paper stack-vision
# Per task, vision: the test seeds (SEEDS overrides). Table III scores Swapping, Drawing and Stacking on 50 seeds
# (100000-100049), its rows the ones beside ours; Push-T's vision table (Table II's protocol) keeps 100.
VSEEDS.swap := 100000:100050
VSEEDS.draw := 100000:100050
VSEEDS.stack := 100000:100050
VSEEDS := $(or $(SEEDS),$(VSEEDS.$(TASK)),100000:100100)
# Per task, vision: the planners of its table. Table III's rows are BC and GPC-RANK K=100, with GPC-OPT, GPC-RANK+OPT
# and the ceiling beside them; Push-T's vision table is Table II's, K=50 as well.
TABLE3_VPLANNERS := vrank-K100 vopt-M25 vrank-opt-10x25
VPLANNERS.swap := $(TABLE3_VPLANNERS)
VPLANNERS.draw := $(TABLE3_VPLANNERS)
VPLANNERS.stack := $(TABLE3_VPLANNERS)
# Per task, vision: how the planning world model's evaluation reads objects where colour cannot (Block Stacking's
# perspective camera): the learned reward's state reader, heights included.
VWM_READER.stack = --pose-reader $(REWARD_CKPT)
# Per task, state: options of the GPC gradient planners (opt, rank-opt) chosen on validation seeds 200000-200049.
# Block Stacking: ascent kept within 1 cm of each proposal, ending at its best iterate (rank-opt 10x30 0.780 against
# 0.562 without: the world model is exploitable far from the policy's chunks; docs/stack.md).
ASCENT.stack := --trust-region 0.01 --keep-best
# State: the world model the planners use (WM_PLAN, per task WM_PLAN.TASK): phase2 (the default) or onpolicy, phase 2
# continued on the policy's own episodes on training seeds as well (the states and chunks it is asked to score).
# Block Stacking: onpolicy, chosen on validation seeds 200000-200049 (3x more accurate on the policy's episodes;
# GPC-RANK K=100 0.608 against 0.556, GPC-RANK+OPT 0.754 / 48% against 0.780 / 36%; docs/stack.md).
WM_PLAN.stack := onpolicy
WM_PLAN_DEFAULT := $(or $(WM_PLAN.$(TASK)),phase2)
WM_PLAN ?= $(WM_PLAN_DEFAULT)
POLICY_OBS := $(or $(POLICY_OBS.$(TASK)),state)
TITLE := $(or $(TITLE.$(TASK)),$(TASK))
# The 186 human demonstrations shipped beside the checkout (the image policy's data; check-sim replays them).
HUMAN_DATA ?= ../shared/data/pusht_human_train.zarr
# SEEDS=START:STOP overrides the test seeds of every profile (cpu and paper: 100000:100100; smoke: a few).
# EXPLORE=0: the paper's ablation, the world model trained on expert data only (own runs and results).
EXPLORE ?= 1
# GOAL=random: GPC's variant, a goal pose drawn per seed: the policy is trained on expert
# demonstrations towards random goals and reads the goal; the world model (goal-agnostic) is shared.
GOAL ?= fixed
# VWM_PLAN: the visual world model the vision planners use: onpolicy (the default, chosen on validation seeds: the
# trained model fine-tuned on GPC-OPT's own recorded episodes as well, then distilled to one step: the model trained
# where the planner goes), student (the trained model's one-step distillation, which records those episodes) or
# teacher (the trained model's 3-step sampler); each has its own results.
VWM_PLAN ?= onpolicy
# VWM_PRECISION: the visual model's training precision (cpu profile). bf16-auto trains in bf16 where the CPU computes it
# natively (about 1.7x faster on 2 cores), else float32. The kept models (artifacts/) trained in float32 on an AVX2 machine, so an
# ablation beside them trains with VWM_PRECISION=32-true: one difference between its arms, the data.
VWM_PRECISION ?= bf16-auto
ifneq ($(GOAL),fixed)
  ifneq ($(filter %vision,$(MAKECMDGOALS)),)
    $(error GOAL=$(GOAL): the vision pipeline has fixed goals only (its image policy reads no goal); drop GOAL)
  endif
endif
ifneq ($(TASK),pusht)
  ifneq ($(filter reproduce-pusht reproduce-pusht-vision,$(MAKECMDGOALS)),)
    $(error TASK=$(TASK): reproduce-pusht and reproduce-pusht-vision are Push-T's spellings; use `make reproduce TASK=$(TASK)` or `make reproduce-vision TASK=$(TASK)`)
  endif
endif
ifeq ($(GOAL),random)
  GOAL_TAG := -random-goal
  POLICY_DIR := $(RUN_DIR)/policy-random-goal
  POLICY_STORE := $(RUN_DIR)/expert-random-goal
else ifeq ($(GOAL),fixed)
  GOAL_TAG :=
  POLICY_DIR := $(RUN_DIR)/policy
  POLICY_STORE := $(RUN_DIR)/expert
else
  $(error GOAL=$(GOAL): use fixed or random)
endif
# Results planned with another model than the task's default keep their own folder.
PLAN_TAG := $(if $(filter $(WM_PLAN),$(WM_PLAN_DEFAULT)),,-wm-$(WM_PLAN))
ifeq ($(EXPLORE),0)
  WM_RUN := $(RUN_DIR)/wm-no-explore
  WM_DATA := --dataset $(RUN_DIR)/expert.zarr
  RESULTS ?= results/$(TASK)-$(PROFILE)-no-explore$(GOAL_TAG)$(PLAN_TAG)
else
  WM_RUN := $(RUN_DIR)/wm
  WM_DATA := --dataset $(RUN_DIR)/expert.zarr --dataset $(RUN_DIR)/explore.zarr
  RESULTS ?= results/$(TASK)-$(PROFILE)$(GOAL_TAG)$(PLAN_TAG)
endif
# BC and the ceiling read no world model, so every WM_PLAN's and EXPLORE's table shares them: one BC and one ceiling
# per profile and goal (a RESULTS given on the command line holds its own).
SHARED := $(if $(filter file,$(origin RESULTS)),results/$(TASK)-$(PROFILE)$(GOAL_TAG),$(RESULTS))

# The paper's vision table (Table II: its K and M) and its ceiling, the true simulator ranking the image policy's proposals.
PAPER_VPLANNERS := vrank-K50 vrank-K100 vopt-M25 vrank-opt-10x25
ARGS.vrank-K50 := --planner rank -K 50
ARGS.vrank-K100 := --planner rank -K 100
# The vision ascent bends each chunk through 4 knots: on validation seeds 200000-200009 (two separately trained model
# sets, docs/results.md) it gained more true reward per ascent than ascending every action, and fooled the visual
# model less (predicted-vs-true correlation +0.38 and +0.44 against +0.16 and +0.08).
VKNOTS ?= 4
ARGS.vopt-M25 := --planner opt -M 25 --knots $(VKNOTS)
ARGS.vrank-opt-10x25 := --planner rank-opt -K 10 -M 25 --knots $(VKNOTS)
ARGS.vgt-sim-K100 := --planner gt-sim -K 100
# The paper's state table (Table I, Push-T): its K and M. `make reproduce-pusht-table1` runs them beside the state table
# (same results folder and ceiling: the rows both have are run once).
PAPER_PLANNERS := rank-K100 rank-K1000 rank-K5000 opt-M30 rank-opt-10x30 rank-opt-20x30 rank-opt-30x20
ARGS.rank-K100 := --planner rank -K 100
ARGS.rank-K1000 := --planner rank -K 1000
ARGS.rank-K5000 := --planner rank -K 5000
ARGS.opt-M30 := --planner opt -M 30 $(ASCENT.$(TASK))
ARGS.rank-opt-10x30 := --planner rank-opt -K 10 -M 30 $(ASCENT.$(TASK))
ARGS.rank-opt-20x30 := --planner rank-opt -K 20 -M 30 $(ASCENT.$(TASK))
ARGS.rank-opt-30x20 := --planner rank-opt -K 30 -M 20 $(ASCENT.$(TASK))

# Profiles: smoke (minutes, used by tests), cpu (default, 2 cores), paper (paper sizes, GPU).
# PLANNERS: the controllers evaluated on the same seeds (result folder names); ARGS.NAME: their gpc eval options.
ifeq ($(PROFILE),smoke)
  EXPERT_EPISODES := 4
  EXPLORE_EPISODES := 4
  POLICY := --profile tiny --max-steps 40
  WM1 := --profile tiny --max-steps 40
  WM2 := --profile tiny --max-steps 10
  RECORD := --seed 70000 --episodes 2 --max-steps 40 --batch 2
  RECORD_HELDOUT := --seed 80000 --episodes 2 --max-steps 40 --batch 2
  WM_ONPOLICY := --profile tiny --max-steps 10
  EVAL := --seeds $(or $(SEEDS),100000:100004) --max-steps 40 --batch 4
  PLANNERS := rank-K4 opt-M3 rank-opt-4x3 cem-8x2 mppi-8x2 grad-4x3
  ARGS.rank-K4 := --planner rank -K 4
  ARGS.opt-M3 := --planner opt -M 3
  ARGS.rank-opt-4x3 := --planner rank-opt -K 4 -M 3
  ARGS.cem-8x2 := --planner cem -K 8 -M 2
  ARGS.mppi-8x2 := --planner mppi -K 8 -M 2
  ARGS.grad-4x3 := --planner grad -K 4 -M 3
  CEILING := gt-sim-K4
  ARGS.gt-sim-K4 := --planner gt-sim -K 4
  TRAIN_ARGS.vgps := --profile tiny --max-steps 20
  TRAIN_ARGS.latent := --profile tiny --max-steps 20
  TRAIN_ARGS.ladi := --profile tiny --max-steps 20
  BASELINES := vgps-K4 dreamer-K4 ladi-K4
  ARGS.vgps-K4 := --planner vgps -K 4
  ARGS.dreamer-K4 := --planner dreamer -K 4
  ARGS.ladi-K4 := --planner ladi -K 4
  BASELINE_GPC := rank-K4
  VBASELINE_GPC := vrank-K3
  VPOLICY := --profile tiny --max-steps 10
  VPOLICY_DATA := $(RUN_DIR)/expert.zarr
  VWM1 := --profile tiny --max-steps 10
  VWM2 := --profile tiny --max-steps 4
  VDISTILL := --profile tiny --max-steps 4
  VREWARD := --profile tiny --max-steps 10
  VEVAL := --seeds $(or $(SEEDS),100000:100002) --max-steps 16 --batch 2
  VPLANNERS := vrank-K3 vopt-M2
  ARGS.vrank-K3 := --planner rank -K 3
  ARGS.vopt-M2 := --planner opt -M 2
  VCEILING := vgt-sim-K3
  ARGS.vgt-sim-K3 := --planner gt-sim -K 3
  VRECORD := vopt-M2
  VRECORD_ARGS := --action-steps 15 --seed 70000 --episodes 2 --max-steps 16 --batch 2
  VWM_ONPOLICY := --profile tiny --max-steps 4
  VPROBE_ARGS := --seeds 200000:200002 --max-steps 16 --batch 2
else ifeq ($(PROFILE),paper)
  EXPERT_EPISODES := 1000
  EXPLORE_EPISODES := 1000
  POLICY := --profile paper
  WM1 := --profile cpu
  WM2 := --profile cpu
  RECORD := --seed 70000 --episodes 2000 --batch 50  # WM_PLAN=onpolicy at paper sizes: not measured yet
  RECORD_HELDOUT := --seed 80000 --episodes 50 --batch 50
  WM_ONPOLICY := --profile cpu --max-steps 10000
  EVAL := --seeds $(or $(SEEDS),100000:100100) --batch 50
  PLANNERS := rank-K100 rank-K1000 opt-M30 rank-opt-10x30 rank-opt-20x30 cem-100x5 mppi-100x5 grad-100x30
  ARGS.cem-100x5 := --planner cem -K 100 -M 5
  ARGS.mppi-100x5 := --planner mppi -K 100 -M 5
  ARGS.grad-100x30 := --planner grad -K 100 -M 30
  CEILING := gt-sim-K100
  ARGS.gt-sim-K100 := --planner gt-sim -K 100
  TRAIN_ARGS.vgps := --profile paper
  TRAIN_ARGS.latent := --profile paper
  TRAIN_ARGS.ladi := --profile paper
  BASELINES := vgps-K100 dreamer-K100 ladi-K100
  BASELINE_GPC := rank-K100 rank-opt-10x30
  VBASELINE_GPC := vrank-K100 vrank-opt-10x25
  VPOLICY := --profile paper
  VPOLICY_DATA := $(if $(filter pusht,$(TASK)),$(HUMAN_DATA),$(RUN_DIR)/expert.zarr)
  VWM1 := --profile paper
  VWM2 := --profile paper
  VDISTILL := --profile cpu
  VREWARD := --profile paper
  VEVAL := --seeds $(VSEEDS) --batch 50
  VPLANNERS := $(or $(VPLANNERS.$(TASK)),$(PAPER_VPLANNERS))
  VCEILING := vgt-sim-K100
  VRECORD := vopt-M25
  VRECORD_ARGS := --action-steps 15 --seed 70000 --episodes 200 --batch 50
  VWM_ONPOLICY := --profile paper --max-steps 5000
  VPROBE_ARGS := --seeds 200000:200050 --max-steps 300 --batch 50
else ifeq ($(PROFILE),cpu)
  EXPERT_EPISODES := $(or $(CPU_EXPERT_EPISODES.$(TASK)),200)
  EXPLORE_EPISODES := 200
  POLICY := --profile cpu --max-steps 3000
  WM1 := --profile cpu --max-steps 6000
  WM2 := --profile cpu --max-steps 2000
  # WM_PLAN=onpolicy: the policy's 900 episodes on training seeds, 6,000 more phase-2 steps (on Block Stacking's
  # validation decisions better than 300 and 4,000; docs/stack.md).
  RECORD := --seed 70000 --episodes 900 --batch 25
  RECORD_HELDOUT := --seed 80000 --episodes 30 --batch 25
  WM_ONPOLICY := --profile cpu --max-steps 6000
  EVAL := --seeds $(or $(SEEDS),100000:100100) --batch 25
  PLANNERS := rank-K10 rank-K100 opt-M30 rank-opt-10x30 cem-100x5 mppi-100x5 grad-10x30
  ARGS.rank-K10 := --planner rank -K 10
  ARGS.cem-100x5 := --planner cem -K 100 -M 5
  ARGS.mppi-100x5 := --planner mppi -K 100 -M 5
  ARGS.grad-10x30 := --planner grad -K 10 -M 30
  CEILING := gt-sim-K100
  ARGS.gt-sim-K100 := --planner gt-sim -K 100
  TRAIN_ARGS.vgps := --profile cpu
  TRAIN_ARGS.latent := --profile cpu
  TRAIN_ARGS.ladi := --profile cpu
  BASELINES := vgps-K100 dreamer-K100 ladi-K100
  BASELINE_GPC := rank-K100 rank-opt-10x30
  VBASELINE_GPC := vrank-K100 vrank-opt-10x25
  # The vision table (issue 19): an image policy on the human demonstrations, the visual world model in one
  # schedule (phase 1 then phase 2: about 2.8 h on a machine with native bf16, 5 h on an AVX2 one), fine-tuned on
  # GPC-OPT's own episodes and distilled to one step, 100 test seeds; the image policy 9,000 steps (0.55 s each on
  # 2 cores with native bf16, about 82 minutes; 1.0 s on AVX2).
  VPOLICY := --profile cpu --max-steps 9000
  VPOLICY_DATA := $(if $(filter pusht,$(TASK)),$(HUMAN_DATA),$(RUN_DIR)/expert.zarr)
  VWM1 := --profile cpu --max-steps 38000 --precision $(VWM_PRECISION) --val-every 5000
  VWM2 := --profile cpu --max-steps 1000 --precision $(VWM_PRECISION) --val-every 1000
  VDISTILL := --profile cpu
  VREWARD := --profile cpu
  VEVAL := --seeds $(VSEEDS) --batch 10
  VPLANNERS := $(or $(VPLANNERS.$(TASK)),$(PAPER_VPLANNERS))
  VCEILING := vgt-sim-K100
  # The on-policy model: GPC-OPT executing its whole ascended chunks (15 actions) on training seeds, 2,000 fine-tuning steps.
  VRECORD := vopt-M25
  VRECORD_ARGS := --action-steps 15 --seed 70000 --episodes 50 --batch 10
  VWM_ONPOLICY := --profile cpu --max-steps 2000 --precision $(VWM_PRECISION) --val-every 1000
  VPROBE_ARGS := --seeds 200000:200010 --max-steps 120 --batch 10
else
  $(error PROFILE=$(PROFILE): use smoke, cpu or paper)
endif

.PHONY: help venv test test-extended test-fast lint types bench reproduce reproduce-pusht reproduce-pusht-table1 reproduce-baselines reproduce-baselines-vision reproduce-vision reproduce-pusht-vision restore-vision keep-vision probe-opt-vision probe-rank-vision check-sim clean

help:
	@echo "make reproduce         collect data and run a task's state pipeline (TASK=pusht|swap|draw|stack, PROFILE=cpu|smoke|paper, EXPLORE=0, GOAL=random, WM_PLAN=phase2|onpolicy|ensemble)"
	@echo "make reproduce-pusht   the same for TASK=pusht (the default)"
	@echo "make reproduce-pusht-table1  the paper's Table I on state Push-T: BC, GPC-RANK K=100/1000/5000, GPC-OPT M=30, GPC-RANK+OPT 10x30/20x30/30x20, the ceiling"
	@echo "make reproduce-vision  the same for image observations (TASK=pusht|swap|draw|stack; fixed goals; visual world model, learned reward; VWM_PLAN=onpolicy|student|teacher, VPLANNERS, VPRECISION, VWM_PRECISION)"
	@echo "make reproduce-baselines  the paper's Table III baselines (V-GPS, DreamerV3-style, LaDi-WM-style) on the state policy's proposals beside GPC-RANK and the ceiling (SEEDS=100000:100050: its protocol)"
	@echo "make reproduce-baselines-vision  the same baselines on the image policy's proposals, beside the vision table's GPC rows (VBASELINE_SEEDS=100000:100050)"
	@echo "make reproduce-pusht-vision   the same for TASK=pusht (the default)"
	@echo "make restore-vision    put a task's vision checkpoints kept in artifacts/TASK-PROFILE/ where their stages look (then go on)"
	@echo "make keep-vision       export a task's finished vision stages (and an unfinished training's state) and their results into artifacts/TASK-PROFILE/"
	@echo "make probe-opt-vision  GPC-OPT through the visual model on validation seeds, replayed in the simulator"
	@echo "make probe-rank-vision how well GPC-RANK's visual model and learned reward order the proposals on validation seeds"
	@echo "make test              lint, type-check and run the test suite (as CI does; make test-extended: the end-to-end checks it leaves out)"
	@echo "make test-fast         lint and the test suite without the slow end-to-end checks (under 2 minutes)"
	@echo "make bench             run the benchmarks and write their latest figures to docs/benchmarks.md"
	@echo "make check-sim         replay and render the shared human data through our simulator"
	@echo "make venv | lint | types | clean   the virtual environment alone; ruff; mypy; remove .venv, runs/ and results/"
	@echo "options for every pipeline: SEEDS=START:STOP (test seeds), WORKERS=N (evaluation processes), BACKEND=ray [RAY_ADDRESS=HOST:PORT], RUN_DIR, RESULTS"

venv: $(STAMP)

# pip byte-compiles one file at a time; compileall does the same work on every core (50 s -> 34 s on 2 cores here).
# Files that do not compile are skipped by both, hence the `|| true`.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q --no-compile "$(TORCH_SPEC)"
	$(BIN)/python -m pip install -q --no-compile -e ".[dev]"
	$(BIN)/python -m compileall -qq -j 0 $(VENV)/lib || true
	touch $(STAMP)

test: lint types
	OMP_NUM_THREADS=1 TORCH_SPEC="$(TORCH_SPEC)" $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder -m "not extended"

# The checks make test leaves out for CI's time (the drawing and stacking smoke pipelines, Ray's fault and store cases).
test-extended: $(STAMP)
	OMP_NUM_THREADS=1 $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile -m extended

test-fast: lint
	$(BIN)/python -m pytest -q -m "not slow"

lint: $(STAMP)
	$(BIN)/ruff check .

# mypy reads the library as it installs (gpc.models, ...): a tree of links maps the user's folders to their package names.
TYPES_TREE := build/typecheck/gpc
types: $(STAMP)
	rm -rf $(TYPES_TREE) && mkdir -p $(TYPES_TREE)
	for f in gpc/*; do ln -s "$(CURDIR)/$$f" $(TYPES_TREE)/$$(basename $$f); done
	ln -s "$(CURDIR)/gpc_cli" $(TYPES_TREE)/cli
	for d in datasets models tasks; do ln -s "$(CURDIR)/$$d" $(TYPES_TREE)/$$d; done
	cd build/typecheck && $(CURDIR)/$(BIN)/mypy --config-file $(CURDIR)/pyproject.toml -p gpc

bench: $(STAMP)
	$(BIN)/python -m benchmarks.run_all --doc docs/benchmarks.md

check-sim: $(STAMP)
	$(BIN)/gpc check-sim --data $(HUMAN_DATA)

# Each stage is a file target: it runs when its output is missing or older than its inputs, and
# collection and training resume from what an interrupted run left.
POLICY_CKPT := $(POLICY_DIR)/checkpoints/last.ckpt
WM_CKPT := $(WM_RUN)-phase2/checkpoints/last.ckpt
TABLE := $(if $(filter cpu1fixed,$(PROFILE)$(EXPLORE)$(GOAL)$(PLAN_TAG)),results/$(TASK)_state.md,$(RESULTS)/$(TASK)_state.md)

$(RUN_DIR)/expert.done: | $(STAMP)
	$(BIN)/gpc collect --task $(TASK) --out $(RUN_DIR)/expert.zarr --episodes $(EXPERT_EPISODES) --seed 0 --workers $(WORKERS) $(SCALE)
	$(BIN)/gpc data info $(RUN_DIR)/expert.zarr
	touch $@

$(RUN_DIR)/explore.done: | $(STAMP)
	$(BIN)/gpc collect --task $(TASK) --explore --out $(RUN_DIR)/explore.zarr --episodes $(EXPLORE_EPISODES) --seed 50000 --workers $(WORKERS) $(SCALE)
	$(BIN)/gpc data info $(RUN_DIR)/explore.zarr
	touch $@

$(RUN_DIR)/expert-random-goal.done: | $(STAMP)
	$(BIN)/gpc collect --task $(TASK) --goal random --no-images --out $(RUN_DIR)/expert-random-goal.zarr --episodes $(EXPERT_EPISODES) \
	  --seed 0 --workers $(WORKERS) $(SCALE)
	$(BIN)/gpc data info $(RUN_DIR)/expert-random-goal.zarr
	touch $@

$(POLICY_DIR).done: $(POLICY_STORE).done
	if [ -f $(POLICY_CKPT) ]; then resume=--resume; fi; \
	$(BIN)/gpc train policy --task $(TASK) --dataset $(POLICY_STORE).zarr --obs $(POLICY_OBS) --goal $(GOAL) $(POLICY) --seed 0 \
	  --out $(POLICY_DIR) $$resume
	touch $@

$(WM_RUN)-phase1.done: $(RUN_DIR)/expert.done $(RUN_DIR)/explore.done
	if [ -f $(WM_RUN)-phase1/checkpoints/last.ckpt ]; then resume=--resume; fi; \
	$(BIN)/gpc train world-model --task $(TASK) --phase 1 $(WM_DATA) $(WM1) --seed 0 --out $(WM_RUN)-phase1 $$resume
	touch $@

$(WM_RUN)-phase2.done: $(WM_RUN)-phase1.done
	if [ -f $(WM_CKPT) ]; then resume=--resume; fi; \
	$(BIN)/gpc train world-model --task $(TASK) --phase 2 $(WM_DATA) $(WM2) --seed 0 --out $(WM_RUN)-phase2 $$resume
	$(BIN)/gpc eval world-model $(WM_CKPT) $(WM_DATA)
	touch $@

# The on-policy model (WM_PLAN=onpolicy): the policy's own episodes on training seeds, each executed chunk one of the
# proposals a planner will score, from the states the policy reaches; phase 2 goes on from the trained model on its data
# and these, and is judged on the policy's episodes of other seeds it never saw.
RECORDED := $(POLICY_DIR)-episodes
ONPOLICY_RUN := $(WM_RUN)-onpolicy$(GOAL_TAG)
ONPOLICY_CKPT := $(ONPOLICY_RUN)/checkpoints/last.ckpt
$(RECORDED).done: $(POLICY_DIR).done
	$(BIN)/gpc record $(POLICY_CKPT) --goal $(GOAL) $(RECORD) --workers $(WORKERS) $(SCALE) --out $(RECORDED).zarr
	$(BIN)/gpc record $(POLICY_CKPT) --goal $(GOAL) $(RECORD_HELDOUT) --workers $(WORKERS) $(SCALE) --out $(RECORDED)-heldout.zarr
	touch $@

$(ONPOLICY_RUN).done: $(RECORDED).done $(WM_RUN)-phase2.done
	if [ -f $(ONPOLICY_CKPT) ]; then resume=--resume; else resume="--init $(WM_CKPT)"; fi; \
	$(BIN)/gpc train world-model --task $(TASK) --phase 2 $(WM_DATA) --dataset $(RECORDED).zarr $(WM_ONPOLICY) --seed 0 \
	  --out $(ONPOLICY_RUN) $$resume
	$(BIN)/gpc eval world-model $(ONPOLICY_CKPT) --dataset $(RECORDED)-heldout.zarr --split all
	touch $@

# WM_PLAN=ensemble: the on-policy model and one more per ENSEMBLE_SEEDS, trained as it is with that seed, planning as
# one (`gpc ensemble`: a candidate's score is the members' mean reward less PESSIMISM times their spread;
# docs/world-models.md, measured on Block Stacking in docs/stack.md).
ENSEMBLE_SEEDS ?= 1 2
PESSIMISM ?= 1
ENSEMBLE_MEMBERS := $(ONPOLICY_RUN) $(foreach s,$(ENSEMBLE_SEEDS),$(ONPOLICY_RUN)-seed$(s))
ENSEMBLE_CKPT := $(ONPOLICY_RUN)-ensemble-p$(PESSIMISM).ckpt
$(ONPOLICY_RUN)-seed%.done: $(RECORDED).done $(WM_RUN)-phase2.done
	if [ -f $(ONPOLICY_RUN)-seed$*/checkpoints/last.ckpt ]; then resume=--resume; else resume="--init $(WM_CKPT)"; fi; \
	$(BIN)/gpc train world-model --task $(TASK) --phase 2 $(WM_DATA) --dataset $(RECORDED).zarr $(WM_ONPOLICY) --seed $* \
	  --out $(ONPOLICY_RUN)-seed$* $$resume
	touch $@

$(ENSEMBLE_CKPT): $(addsuffix .done,$(ENSEMBLE_MEMBERS))
	$(BIN)/gpc ensemble $(addsuffix /checkpoints/last.ckpt,$(ENSEMBLE_MEMBERS)) --pessimism $(PESSIMISM) --out $@ --overwrite

ifeq ($(WM_PLAN),onpolicy)
  PLAN_DONE := $(ONPOLICY_RUN).done
  PLAN_CKPT := $(ONPOLICY_CKPT)
  PLAN_DATA := $(WM_DATA) --dataset $(RECORDED).zarr
  PLAN_DATA_DONE := $(RECORDED).done
  PLAN_DATA_TAG := -onpolicy
else ifeq ($(WM_PLAN),ensemble)
  PLAN_DONE := $(ENSEMBLE_CKPT)
  PLAN_CKPT := $(ENSEMBLE_CKPT)
  PLAN_DATA := $(WM_DATA) --dataset $(RECORDED).zarr
  PLAN_DATA_DONE := $(RECORDED).done
  PLAN_DATA_TAG := -onpolicy
else ifeq ($(WM_PLAN),phase2)
  PLAN_DONE := $(WM_RUN)-phase2.done
  PLAN_CKPT := $(WM_CKPT)
  PLAN_DATA := $(WM_DATA)
else
  $(error WM_PLAN=$(WM_PLAN): use phase2, onpolicy or ensemble)
endif

# One eval per controller (NAME, results dir, prerequisites, gpc eval arguments), each skipped
# once its summary is newer than the checkpoints it used; a stopped eval resumes its saved groups,
# results of other checkpoints are replaced (--resume --overwrite).
# eval_rule NAME,FOLDER,PREREQUISITES,ARGS,SEEDS: one controller's results. A folder holds one seed set: results for
# other SEEDS would look up to date and be printed under the new seeds' title, so the folder is stamped with its seed
# set (or, unstamped, read from the results it holds) and another one refused; order-only, so it never makes one stale.
define eval_rule
$(2)/$(1)/summary.json: $(3) | $(2)/.seeds-$(subst :,-,$(5))
	$(BIN)/gpc eval $(4) --workers $(WORKERS) $(SCALE) --out $(2)/$(1) --resume --overwrite
endef
.seeds-%:
	@$(BIN)/python -c 'import json, pathlib, sys; folder, want = pathlib.Path(sys.argv[1]), sys.argv[2].replace("-", ":"); \
	seeds = [json.loads(p.read_text()).get("run", {}).get("config", {}).get("seeds") for p in folder.glob("*/summary.json")]; \
	held = {p.name[7:].replace("-", ":") for p in folder.glob(".seeds-*")} | {f"{min(s)}:{max(s) + 1}" for s in seeds if s}; \
	held.discard(want); held and sys.exit(f"{folder} holds results for seeds {held.pop()}, not {want} (SEEDS): " \
	"give another RESULTS, or remove that folder")' $(@D) $(patsubst .seeds-%,%,$(@F))
	@mkdir -p $(@D) && touch $@
$(eval $(call eval_rule,bc,$(SHARED),$(POLICY_DIR).done,$(POLICY_CKPT) $(EVAL) --goal $(GOAL),$(word 2,$(EVAL))))
# The ground-truth ceiling uses no learned world model, so only the policy makes it stale (in PLANNERS too, if put there).
uses_wm = $(if $(findstring gt-sim,$(1)),,$(2))
$(foreach n,$(PLANNERS),$(eval $(call eval_rule,$(n),$(RESULTS),$(POLICY_DIR).done $(call uses_wm,$(n),$(PLAN_DONE)),\
  $(POLICY_CKPT) $(ARGS.$(n)) $(call uses_wm,$(n),--world-model $(PLAN_CKPT)) $(EVAL) --goal $(GOAL),$(word 2,$(EVAL)))))
$(eval $(call eval_rule,$(CEILING),$(SHARED),$(POLICY_DIR).done,$(POLICY_CKPT) $(ARGS.$(CEILING)) $(EVAL) --goal $(GOAL),$(word 2,$(EVAL))))

$(TABLE): $(SHARED)/bc/summary.json $(foreach n,$(PLANNERS),$(RESULTS)/$(n)/summary.json) $(SHARED)/$(CEILING)/summary.json
	$(BIN)/gpc compare $(foreach n,$(PLANNERS),$(RESULTS)/$(n)) $(SHARED)/$(CEILING) --baseline $(SHARED)/bc \
	  --ceiling $(SHARED)/$(CEILING) $(PAPER_STATE.$(TASK)) --out $@ \
	  --title "State $(TITLE), PROFILE=$(PROFILE), seeds $(word 2,$(EVAL)): planners against BC (policy trained on expert data, $(GOAL) goal)"

# The paper's Table III baselines on the same proposals (issue 49): V-GPS ranks the policy's K proposals by an IQL
# Q-function trained on the world model's data with the task's reward; beside GPC-RANK at the same K and the ceiling.
ARGS.vgps-K100 := --planner vgps -K 100
ARGS.dreamer-K100 := --planner dreamer -K 100
ARGS.ladi-K100 := --planner ladi -K 100
# Each baseline's model (a run beside the world model's, on the planning model's data): what trains it, and which planner ranks with it.
TRAIN.vgps := value
TRAIN.latent := latent-world-model
TRAIN.ladi := latent-world-model --kind ladi
MODEL.vgps := vgps
MODEL.dreamer := latent
MODEL.ladi := ladi
model_of = $(MODEL.$(firstword $(subst -, ,$(1))))
baseline_run = $(subst /wm,/$(1),$(WM_RUN))$(GOAL_TAG)$(PLAN_DATA_TAG)
BASELINE_TABLE := $(RESULTS)/$(TASK)_baselines.md
define baseline_model
$(call baseline_run,$(1)).done: $(POLICY_DIR).done $(RUN_DIR)/expert.done $(RUN_DIR)/explore.done $(PLAN_DATA_DONE)
	if [ -f $(call baseline_run,$(1))/checkpoints/last.ckpt ]; then resume=--resume; fi; \
	$(BIN)/gpc train $(TRAIN.$(1)) --task $(TASK) $(PLAN_DATA) --policy $(POLICY_CKPT) $(TRAIN_ARGS.$(1)) --seed 0 \
	  --out $(call baseline_run,$(1)) $$$$resume
	touch $$@
endef
$(foreach m,vgps latent ladi,$(eval $(call baseline_model,$(m))))
$(foreach n,$(BASELINES),$(eval $(call eval_rule,$(n),$(RESULTS),$(POLICY_DIR).done $(call baseline_run,$(call model_of,$(n))).done,\
  $(POLICY_CKPT) $(ARGS.$(n)) --world-model $(call baseline_run,$(call model_of,$(n)))/checkpoints/last.ckpt $(EVAL) --goal $(GOAL),$(word 2,$(EVAL)))))
# GPC's rows beside them (their rules are the state table's, unless PLANNERS leaves them out)
$(foreach n,$(filter-out $(PLANNERS),$(BASELINE_GPC)),$(eval $(call eval_rule,$(n),$(RESULTS),$(POLICY_DIR).done $(PLAN_DONE),\
  $(POLICY_CKPT) $(ARGS.$(n)) --world-model $(PLAN_CKPT) $(EVAL) --goal $(GOAL),$(word 2,$(EVAL)))))
$(BASELINE_TABLE): $(SHARED)/bc/summary.json $(foreach n,$(BASELINES) $(BASELINE_GPC),$(RESULTS)/$(n)/summary.json) \
  $(SHARED)/$(CEILING)/summary.json
	$(BIN)/gpc compare $(foreach n,$(BASELINES) $(BASELINE_GPC),$(RESULTS)/$(n)) $(SHARED)/$(CEILING) --baseline $(SHARED)/bc \
	  --ceiling $(SHARED)/$(CEILING) --out $@ \
	  --title "State $(TITLE), PROFILE=$(PROFILE), seeds $(word 2,$(EVAL)): the baselines against GPC-RANK on the same proposals"
reproduce-baselines: $(BASELINE_TABLE)
	@cat $(BASELINE_TABLE)

reproduce: $(TABLE)
	@cat $(TABLE)

reproduce-pusht: reproduce

# Table I's K and M beside the paper's row, in their own table (`BACKEND=ray` spreads it: issue 47, docs/scale-out.md).
reproduce-pusht-table1:
	$(MAKE) reproduce TASK=pusht PLANNERS="$(PAPER_PLANNERS)" TABLE=$(patsubst %_state.md,%_table1.md,$(TABLE))

# The vision pipeline: an image policy, the visual (EDM) world model (phase 1, phase 2, then its one-step student)
# and the learned image reward; each stage resumes from what an interrupted run left.
VPOLICY_CKPT := $(RUN_DIR)/vpolicy/checkpoints/last.ckpt
VWM_RUN := $(WM_RUN)-visual
VWM_CKPT := $(VWM_RUN)-phase2/checkpoints/last.ckpt
VSTUDENT_CKPT := $(VWM_RUN)-1step/checkpoints/last.ckpt
VONPOLICY_STUDENT_CKPT := $(VWM_RUN)-onpolicy-1step/checkpoints/last.ckpt
ifeq ($(VWM_PLAN),student)
  VPLAN_DONE := $(VWM_RUN)-1step.done
  VPLAN_CKPT := $(VSTUDENT_CKPT)
  VRESULTS := $(RESULTS)-vision
else ifeq ($(VWM_PLAN),teacher)
  VPLAN_DONE := $(VWM_RUN)-phase2.done
  VPLAN_CKPT := $(VWM_CKPT)
  VRESULTS := $(RESULTS)-vision-teacher
else ifeq ($(VWM_PLAN),onpolicy)
  VPLAN_DONE := $(VWM_RUN)-onpolicy-1step.done
  VPLAN_CKPT := $(VONPOLICY_STUDENT_CKPT)
  VRESULTS := $(RESULTS)-vision-onpolicy
else
  $(error VWM_PLAN=$(VWM_PLAN): use student, teacher or onpolicy)
endif
# The visual model asks for bf16 rollouts, which run where the hardware computes bf16 natively: other numbers than
# float32's. Its planners pin float32 (every row of the table was measured so), so their results do not depend on the
# machine and kept ones resume on any; VPRECISION=bf16-auto is faster where bf16 is native (its own results folder).
VPRECISION ?= 32-true
VRESULTS := $(VRESULTS)$(if $(filter-out 32-true,$(VPRECISION)),-$(VPRECISION))
# BC and the ceiling read no world model, so every VWM_PLAN's table shares them, and so does the exploration ablation
# (EXPLORE=0 retrains only the world model): one BC and one ceiling per profile and goal.
VSHARED := $(SHARED)-vision
REWARD_CKPT := $(RUN_DIR)/reward/checkpoints/last.ckpt
VTABLE := $(if $(filter cpu1onpolicy32-true,$(PROFILE)$(EXPLORE)$(VWM_PLAN)$(VPRECISION)),results/$(TASK)_vision.md,$(VRESULTS)/$(TASK)_vision.md)
VPOLICY_DEPS := $(if $(filter $(RUN_DIR)/%,$(VPOLICY_DATA)),$(RUN_DIR)/expert.done)

$(RUN_DIR)/vpolicy.done: $(VPOLICY_DEPS) | $(STAMP)
	if [ -f $(VPOLICY_CKPT) ]; then resume=--resume; fi; \
	$(BIN)/gpc train policy --task $(TASK) --dataset $(VPOLICY_DATA) --obs image $(VPOLICY) --seed 0 --out $(RUN_DIR)/vpolicy $$resume
	touch $@

$(VWM_RUN)-phase1.done: $(RUN_DIR)/expert.done $(RUN_DIR)/explore.done
	if [ -f $(VWM_RUN)-phase1/checkpoints/last.ckpt ]; then resume=--resume; fi; \
	$(BIN)/gpc train world-model --task $(TASK) --obs image --phase 1 $(WM_DATA) $(VWM1) --seed 0 --out $(VWM_RUN)-phase1 $$resume
	touch $@

$(VWM_RUN)-phase2.done: $(VWM_RUN)-phase1.done
	if [ -f $(VWM_CKPT) ]; then resume=--resume; else resume="--init $(VWM_RUN)-phase1/checkpoints/last.ckpt"; fi; \
	$(BIN)/gpc train world-model --task $(TASK) --obs image --phase 2 $(WM_DATA) $(VWM2) --seed 0 --out $(VWM_RUN)-phase2 $$resume
	$(BIN)/gpc eval world-model $(VWM_CKPT) $(WM_DATA)
	touch $@

$(VWM_RUN)-1step.done: $(VWM_RUN)-phase2.done
	if [ -f $(VSTUDENT_CKPT) ]; then resume=--resume; fi; \
	$(BIN)/gpc train world-model --task $(TASK) --distill $(VWM_CKPT) --sampler-steps 1 $(WM_DATA) $(VDISTILL) --seed 0 \
	  --out $(VWM_RUN)-1step $$resume
	$(BIN)/gpc eval world-model $(VSTUDENT_CKPT) $(WM_DATA)
	touch $@

$(RUN_DIR)/reward.done: $(RUN_DIR)/expert.done $(RUN_DIR)/explore.done
	if [ -f $(REWARD_CKPT) ]; then resume=--resume; fi; \
	$(BIN)/gpc train reward --task $(TASK) --dataset $(RUN_DIR)/expert.zarr --dataset $(RUN_DIR)/explore.zarr $(VREWARD) --seed 0 \
	  --out $(RUN_DIR)/reward $$resume
	touch $@

# The on-policy model (VWM_PLAN=onpolicy): the student plans with GPC-OPT on training seeds, executing each ascended
# chunk whole (`gpc record`: every action the reward judged, with its true outcome); the teacher is fine-tuned on those
# episodes beside its own data, then distilled again.
VRECORDED := $(VWM_RUN)-opt-episodes.zarr
VONPOLICY_CKPT := $(VWM_RUN)-onpolicy/checkpoints/last.ckpt
$(VWM_RUN)-opt-episodes.done: $(RUN_DIR)/vpolicy.done $(VWM_RUN)-1step.done $(RUN_DIR)/reward.done
	$(BIN)/gpc record $(VPOLICY_CKPT) $(ARGS.$(VRECORD)) --world-model $(VSTUDENT_CKPT) --reward learned \
	  --reward-checkpoint $(REWARD_CKPT) --precision $(VPRECISION) $(VRECORD_ARGS) --workers $(WORKERS) $(SCALE) --out $(VRECORDED)
	touch $@

$(VWM_RUN)-onpolicy.done: $(VWM_RUN)-opt-episodes.done $(VWM_RUN)-phase2.done
	if [ -f $(VONPOLICY_CKPT) ]; then resume=--resume; else resume="--init $(VWM_CKPT)"; fi; \
	$(BIN)/gpc train world-model --task $(TASK) --obs image --phase 2 $(WM_DATA) --dataset $(VRECORDED) $(VWM_ONPOLICY) --seed 0 \
	  --out $(VWM_RUN)-onpolicy $$resume
	touch $@

$(VWM_RUN)-onpolicy-1step.done: $(VWM_RUN)-onpolicy.done
	if [ -f $(VONPOLICY_STUDENT_CKPT) ]; then resume=--resume; fi; \
	$(BIN)/gpc train world-model --task $(TASK) --distill $(VONPOLICY_CKPT) --sampler-steps 1 $(WM_DATA) --dataset $(VRECORDED) $(VDISTILL) \
	  --seed 0 --out $(VWM_RUN)-onpolicy-1step $$resume
	$(BIN)/gpc eval world-model $(VONPOLICY_STUDENT_CKPT) $(WM_DATA) --dataset $(VRECORDED) $(VWM_READER.$(TASK))
	touch $@

VDONE := $(RUN_DIR)/vpolicy.done $(VPLAN_DONE) $(RUN_DIR)/reward.done
$(eval $(call eval_rule,bc,$(VSHARED),$(RUN_DIR)/vpolicy.done,$(VPOLICY_CKPT) $(VEVAL),$(word 2,$(VEVAL))))
$(foreach n,$(VPLANNERS),$(eval $(call eval_rule,$(n),$(VRESULTS),$(VDONE),\
  $(VPOLICY_CKPT) $(ARGS.$(n)) --world-model $(VPLAN_CKPT) --reward learned --reward-checkpoint $(REWARD_CKPT) \
  --precision $(VPRECISION) $(VEVAL),$(word 2,$(VEVAL)))))
$(eval $(call eval_rule,$(VCEILING),$(VSHARED),$(RUN_DIR)/vpolicy.done,$(VPOLICY_CKPT) $(ARGS.$(VCEILING)) $(VEVAL),$(word 2,$(VEVAL))))

$(VTABLE): $(VSHARED)/bc/summary.json $(foreach n,$(VPLANNERS),$(VRESULTS)/$(n)/summary.json) $(VSHARED)/$(VCEILING)/summary.json
	$(BIN)/gpc compare $(foreach n,$(VPLANNERS),$(VRESULTS)/$(n)) $(VSHARED)/$(VCEILING) --baseline $(VSHARED)/bc \
	  --ceiling $(VSHARED)/$(VCEILING) $(PAPER_VISION.$(TASK)) --out $@ \
	  --title "Vision $(TITLE), PROFILE=$(PROFILE), seeds $(word 2,$(VEVAL)): planners against BC ($(VWM_PLAN) world model)"

reproduce-vision: $(VTABLE)
	@cat $(VTABLE)

# The Table III baselines on the image policy's proposals (issue 49): each model trained on the visual world model's
# data, reading what the image policy reads; evaluated on VBASELINE_SEEDS (Table III's 50) and paired there with the
# vision table's BC, GPC rows and ceiling (evaluated on more seeds: read on those alone, not run again).
VBASELINE_SEEDS ?= $(if $(filter smoke,$(PROFILE)),$(word 2,$(VEVAL)),100000:100050)
VBEVAL := --seeds $(VBASELINE_SEEDS) $(wordlist 3,$(words $(VEVAL)),$(VEVAL))
VBRESULTS := $(VSHARED)-baselines
VBTABLE := $(VBRESULTS)/$(TASK)_baselines_vision.md
VBASELINES := $(addprefix v,$(BASELINES))
vbaseline_run = $(RUN_DIR)/$(1)-visual
define vbaseline_model
$(call vbaseline_run,$(1)).done: $(RUN_DIR)/vpolicy.done $(RUN_DIR)/expert.done $(RUN_DIR)/explore.done
	if [ -f $(call vbaseline_run,$(1))/checkpoints/last.ckpt ]; then resume=--resume; fi; \
	$(BIN)/gpc train $(TRAIN.$(1)) --task $(TASK) $(WM_DATA) --policy $(VPOLICY_CKPT) $(TRAIN_ARGS.$(1)) --seed 0 \
	  --out $(call vbaseline_run,$(1)) $$$$resume
	touch $$@
endef
$(foreach m,vgps latent ladi,$(eval $(call vbaseline_model,$(m))))
$(foreach n,$(VBASELINES),$(eval $(call eval_rule,$(n),$(VBRESULTS),$(RUN_DIR)/vpolicy.done \
  $(call vbaseline_run,$(call model_of,$(n:v%=%))).done,$(VPOLICY_CKPT) $(ARGS.$(n:v%=%)) \
  --world-model $(call vbaseline_run,$(call model_of,$(n:v%=%)))/checkpoints/last.ckpt $(VBEVAL),$(VBASELINE_SEEDS))))
$(VBTABLE): $(VSHARED)/bc/summary.json $(foreach n,$(VBASELINES),$(VBRESULTS)/$(n)/summary.json) \
  $(foreach n,$(VBASELINE_GPC),$(VRESULTS)/$(n)/summary.json) $(VSHARED)/$(VCEILING)/summary.json
	$(BIN)/gpc compare $(foreach n,$(VBASELINES),$(VBRESULTS)/$(n)) $(foreach n,$(VBASELINE_GPC),$(VRESULTS)/$(n)) \
	  $(VSHARED)/$(VCEILING) --baseline $(VSHARED)/bc --ceiling $(VSHARED)/$(VCEILING) --seeds $(VBASELINE_SEEDS) \
	  $(PAPER_VISION.$(TASK)) --out $@ \
	  --title "Vision $(TITLE), PROFILE=$(PROFILE), seeds $(VBASELINE_SEEDS): the baselines against GPC on the image policy's proposals"

reproduce-baselines-vision: $(VBTABLE)
	@cat $(VBTABLE)

reproduce-pusht-vision: reproduce-vision

# restore-vision: the trained vision checkpoints kept in git (artifacts/$(TASK)-$(PROFILE)/, artifacts/README.md) put where
# their stages look, so a machine that did not train them goes on from there: NAME.ckpt (a `gpc export`) is a finished
# stage, marked done; NAME.resume.ckpt (Lightning's whole state) a training that resumes. The evaluations kept with them
# (results/NAME/: finished, or the groups a stopped one saved) come back after them, so make finds the finished ones up
# to date and resumes the rest. Nothing already in runs/ or results/ is replaced.
ARTIFACTS := artifacts/$(TASK)-$(PROFILE)
ARTIFACT_STAGES := vpolicy reward $(foreach s,phase1 phase2 1step onpolicy onpolicy-1step,$(notdir $(VWM_RUN))-$(s)) \
  $(foreach m,vgps latent ladi,$(notdir $(call vbaseline_run,$(m))))
KEPT_RESULTS := $(sort $(VSHARED) $(VRESULTS) $(VBRESULTS))
# A kept on-policy teacher stands for its recording too (the 9 MB store of small chunk files is not kept): that stamp
# goes after those of the stages it was recorded with and before the teacher's.
RECORDED_STAGE := $(notdir $(VWM_RUN))-onpolicy
restore-vision: $(RUN_DIR)/expert.done $(RUN_DIR)/explore.done
	@for name in $(ARTIFACT_STAGES); do \
	  last=$(RUN_DIR)/$$name/checkpoints/last.ckpt; \
	  for kind in ckpt resume.ckpt; do \
	    src=$(ARTIFACTS)/$$name.$$kind; [ -f $$src ] || continue; \
	    if [ -e $$last ]; then echo "kept $$last"; else mkdir -p $$(dirname $$last) && cp $$src $$last && echo "restored $$last"; fi; \
	    if [ $$kind = ckpt ] && cmp -s $$src $$last; then \
	      if [ $$name = $(RECORDED_STAGE) ] && [ ! -e $(VWM_RUN)-opt-episodes.done ]; then touch $(VWM_RUN)-opt-episodes.done; fi; \
	      touch $(RUN_DIR)/$$name.done; fi; \
	  done; \
	done; \
	for res in $(KEPT_RESULTS); do for src in $(ARTIFACTS)/results/$$(basename $$res)/*/; do \
	  [ -d $$src ] || continue; dst=$$res/$$(basename $$src); \
	  if [ -e $$dst ]; then echo "kept $$dst"; else mkdir -p $$res && cp -r $$src $$dst && echo "restored $$dst"; \
	    find $$dst -name summary.json -exec touch {} +; fi; \
	done; done

# keep-vision: the other way, before a sitting ends: each finished stage exported into artifacts/ (and its runs/ copy
# replaced by the export, the trained file kept beside as trained.ckpt, so results measured from here on key on the
# same bytes a restored machine has), an unfinished training's last checkpoint kept whole to resume, and the
# evaluations' results (finished or their saved groups, no videos). Then commit. A training state over KEEP_RESUME_MB
# (the image policy's: 123 MB, Adam's moments of both weight copies) stays behind: that stage must finish in one sitting.
KEEP_RESUME_MB ?= 32
# The exports store the network's weights in float16 (`gpc export --half`: the image policy 15 MB, not 30), so a task's
# kept stages fit about 40 MB; the runs/ copy becomes that export, so every figure from here on is measured with it.
# Push-T's kept files predate this and stay float32. KEEP_EXPORT= keeps float32.
KEEP_EXPORT ?= --half
keep-vision: | $(STAMP)
	@mkdir -p $(ARTIFACTS); for name in $(ARTIFACT_STAGES); do \
	  dir=$(RUN_DIR)/$$name/checkpoints; [ -f $$dir/last.ckpt ] || continue; \
	  if [ -f $(RUN_DIR)/$$name.done ]; then \
	    cmp -s $$dir/last.ckpt $(ARTIFACTS)/$$name.ckpt && continue; \
	    $(BIN)/gpc export $$dir/last.ckpt --out $(ARTIFACTS)/$$name.ckpt --overwrite $(KEEP_EXPORT) || exit 1; \
	    mv $$dir/last.ckpt $$dir/trained.ckpt && cp $(ARTIFACTS)/$$name.ckpt $$dir/last.ckpt; \
	    rm -f $(ARTIFACTS)/$$name.resume.ckpt; \
	  elif [ $$(du -m $$dir/last.ckpt | cut -f1) -gt $(KEEP_RESUME_MB) ]; then \
	    echo "not kept: $$dir/last.ckpt ($$(du -m $$dir/last.ckpt | cut -f1) MB of training state; KEEP_RESUME_MB=$(KEEP_RESUME_MB))"; \
	  else \
	    cp $$dir/last.ckpt $(ARTIFACTS)/$$name.resume.ckpt && echo "kept $(ARTIFACTS)/$$name.resume.ckpt (resumes)"; \
	  fi; \
	done; \
	for res in $(KEPT_RESULTS); do for src in $$res/*/; do \
	  [ -d $$src/.groups ] || [ -f $$src/summary.json ] || continue; \
	  dst=$(ARTIFACTS)/results/$$(basename $$res)/$$(basename $$src); rm -rf $$dst.new && mkdir -p $$dst.new && \
	  cp -r $$src/. $$dst.new/ && find $$dst.new -name '*.mp4' -delete && rm -rf $$dst && mv $$dst.new $$dst; \
	done; done

# probe-opt-vision: GPC-OPT (the VRECORD planner) with the chosen visual model on validation seeds, every ascent iterate
# replayed in the true simulator: predicted against true gain, the share of fooled ascents (docs/results.md).
VPROBE := $(VRESULTS)/ascent-$(VRECORD).md
$(VPROBE): $(VDONE)
	$(BIN)/gpc eval ascent $(VPOLICY_CKPT) $(ARGS.$(VRECORD)) --world-model $(VPLAN_CKPT) --reward learned \
	  --reward-checkpoint $(REWARD_CKPT) --precision $(VPRECISION) $(VPROBE_ARGS) --out $@

probe-opt-vision: $(VPROBE)
	@cat $(VPROBE)

# probe-rank-vision: how well GPC-RANK's scorer (the visual model and the learned reward) orders the image policy's
# K=100 proposals at BC's decisions on validation seeds, each proposal replayed in the true simulator: the check a
# vision recipe needs before its test seeds (Triangle Drawing's first recipe ranked at chance; docs/tasks.md).
VRANK_PROBE := $(VRESULTS)/ranking-vrank-K100.md
$(VRANK_PROBE): $(VDONE)
	$(BIN)/gpc eval ranking $(VPOLICY_CKPT) --scorer rank=$(VPLAN_CKPT) --reward learned --reward-checkpoint $(REWARD_CKPT) \
	  --precision $(VPRECISION) -K 100 $(VPROBE_ARGS) --out $@

probe-rank-vision: $(VRANK_PROBE)
	@cat $(VRANK_PROBE)

clean:
	rm -rf $(VENV) runs results .pytest_cache
