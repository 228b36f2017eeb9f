# Two commands on a fresh machine: `make demo` and `make test`. Both create .venv when missing or stale.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo models hyp-models test test-slow bench bench-zstep interaction batch ceiling safety results results-full cross-world interactive-models candidate-models clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]'
	touch $(STAMP)

# The learning pipeline, in models/ and data/small/: the dataset, the teacher, the certified student, the student
# distilled further on the world's answers to mpc=interactive's candidate plans at the states its closed loop visits
# with cv (bench.candidates, seeds from 30,000,000; without it the student's interactive step merges courteously in none
# of 160 tuning worlds, with it in 44%: docs/archive/2026-11-studies.md), the states the student's interactive step
# linearises at (seeds from 5,000,000, kept from data and tests), and the gradient surrogate trained and tested on them.
# $(1)..$(6): each job's size overrides (none: its default in conf/, the full recipe).
define MODELS
	$(BIN)/make-dataset $(1)
	$(BIN)/distill model=teacher $(2)
	$(BIN)/distill model=student $(3)
	$(BIN)/python -m bench.candidates "drive=[cv]" out_dir=data/small name=candidates $(4)
	$(BIN)/distill model=student dataset=interactive dataset_dir=data/small/candidates init_from=models/student.ckpt eval_dir=data/small $(5)
	$(BIN)/planner scenario=dense gradients=student mpc=interactive method=admm episodes=8 seed=5000000 plots=false record_dir=data/small/iterates
	$(BIN)/surrogate data.iterates=data/small/iterates $(6)
endef

# make demo's sizes: each training smaller than its job's default, so that the demo fits 10 minutes on 2 cores (bench.demo
# prints by how much); `make models` trains the same pipeline at the full recipe.
DEMO_DATASET := dataset.episodes=80
DEMO_TEACHER := model.epochs=1
DEMO_STUDENT := model.epochs=4 model.certificate.samples=3000
DEMO_CANDIDATES := worlds=10
DEMO_FINETUNE := model.epochs=3
DEMO_SURROGATE := data.iterate_states=300 data.dataset_windows=600 data.plan_states=300 trainer.max_epochs=8
comma := ,
DEMO_SHRUNK := $(foreach o,$(DEMO_DATASET),make_dataset:$(o)) $(foreach o,$(DEMO_TEACHER),distill$(comma)model=teacher:$(o)) \
	$(foreach o,$(DEMO_STUDENT),distill$(comma)model=student:$(o)) $(foreach o,$(DEMO_CANDIDATES),candidates:$(o)) \
	$(foreach o,$(DEMO_FINETUNE),distill$(comma)model=student$(comma)dataset=interactive:$(o)) \
	$(foreach o,$(DEMO_SURROGATE),surrogate:$(o))
DEMO := outputs/demo
DEMO_WORLDS := 4

# The pipeline at demo size, then the dense headline: on 4 held-out dense worlds (seeds from 2,000,000) the clairvoyant
# ceiling and ADMM's interactive step (mpc=interactive) with cv, the learned student and its gradient surrogate;
# compare's accuracy-against-speed table; the headline table, how far each training was shrunk, and a picture of one
# merge ($(DEMO)/merge.png: the road, the cars, the ego's plan, the outcome). Each training is cut to between 4% and 50%
# of its job's default (bench.demo prints each). Timed from a fresh clone on a quiet 2-core machine (2026-12-02, commit
# ee61942): 6 min 57 s wall, the venv included; 439 s user + 55 s sys.
# Every job of one `make demo` (or `make models`) is a child of one MLflow parent run named after the command and its start.
demo: export MLFLOW_RUN_GROUP := make demo $(shell date -u +%Y-%m-%dT%H:%M:%SZ)
demo: $(STAMP)
	$(call MODELS,$(DEMO_DATASET),$(DEMO_TEACHER),$(DEMO_STUDENT),$(DEMO_CANDIDATES),$(DEMO_FINETUNE),$(DEMO_SURROGATE))
	$(BIN)/ceiling scenario=dense episodes=$(DEMO_WORLDS) seed=2000000 out_dir=$(DEMO)
	for g in cv student surrogate; do $(BIN)/planner scenario=dense mpc=interactive gradients=$$g method=admm episodes=$(DEMO_WORLDS) \
		seed=2000000 plots=false out_dir=$(DEMO)/$$g || exit 1; done
	$(BIN)/compare
	$(BIN)/python -m bench.demo $(DEMO) scenario=dense --shrunk $(DEMO_SHRUNK)

# make demo's models at the full recipe, every job at its default;
# not yet timed (the old demo's sizes, smaller, took about 20 minutes on 2 cores).
models: export MLFLOW_RUN_GROUP := make models $(shell date -u +%Y-%m-%dT%H:%M:%SZ)
models: $(STAMP)
	$(call MODELS)

# The hypothesis models (issue 72): a dataset of its own (dataset=small, 160 episodes, in data/hyp/small), the teacher
# given a hypothesis of yielding per car with its belief head, and its certified GELU student, both in models/ beside
# make demo's; `planner gradients=student_hyp mpc=interactive` then plans with the contingency step. Cut to 4 epochs each
# (of 12 and 15) and 3000 certificate samples; figures in docs/findings.md, section 6.
hyp-models: $(STAMP)
	$(BIN)/make-dataset out_dir=data/hyp plot_episodes=0
	$(BIN)/distill model=teacher_hyp dataset_dir=data/hyp/small model.epochs=4
	$(BIN)/distill model=student_hyp dataset_dir=data/hyp/small model.epochs=4 model.certificate.samples=3000

# The suite on both cores (pytest-xdist; each file on one worker, so a file's module fixtures are built once), but the
# end-to-end tests marked slow, which `make test-slow` runs (CI runs both). No test waits on the clock.
test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -n 2 --dist loadfile -m "not slow" --durations=15

test-slow: $(STAMP)
	$(BIN)/python -m pytest -n 2 --dist loadfile -m slow

# One MPC step per gradient source on saved planning states, single-threaded, with the ratios (needs `make demo` models).
bench: $(STAMP)
	$(BIN)/python -m bench.step_time

# Our SQP Z-step against the paper's PyGranso BFGS-SQP on the same states (slow: minutes per state).
bench-zstep: $(STAMP)
	$(BIN)/python -m bench.zstep_compare

# Counterfactual interaction benchmark: every predictor's and gradient source's response to paired ego plans against the
# world's true response on held-out branches (about a minute for cv, analytic, reference, student; teacher is slower).
interaction: $(STAMP)
	$(BIN)/evaluate-interaction

# 1000 held-out random merges (seeds from 2,000,000) with the trained surrogate, both methods, in parallel (joblib), one
# MLflow run per method; needs `make demo` models; about 40 minutes on 2 cores.
batch: $(STAMP)
	$(BIN)/planner scenario=random episodes=1000 seed=2000000 gradients=surrogate method=both

# The clairvoyant ceiling on 200 held-out dense worlds (seeds from 2,000,000) and with every driver stubborn: the strategy
# library, then its cross-entropy refinement; about 10 minutes on 2 cores (5.7 processor seconds a world, measured on 12
# tuning worlds on a busy machine; docs/findings.md). The same for other scenarios: `ceiling scenario=dense_deadline
# episodes=200`; `backend=ray ray.address=auto` for a cluster; a planner batch's runs as further
# starts: 'starts=["<its out_dir>/steps/admm_{seed}.csv"]' (planner/batch.py writes them; `make results` passes them all).
ceiling: $(STAMP)
	$(BIN)/ceiling scenario=dense episodes=200 seed=2000000

# Collisions (issue 74): the rules row (mpc=courteous) and mpc=interactive with cv, the student and the surrogate, ADMM on
# 500 fresh dense worlds each (seeds from 40,000,000) and on 100 where no driver yields (scenario.cooperation=stubborn,
# seeds from 41,000,000): outputs/safety/<time>/safety.md, collisions with 95% intervals and the seeds that collided;
# exit 2 on any collision or crash. Needs `make demo`'s models. SAFETY_WORLDS/SAFETY_STUBBORN size it, SAFETY takes any
# other override. About 16 minutes on 2 cores (0.2-0.5 s a world; docs/findings.md, "Collisions").
# On a Ray cluster: make safety SAFETY_WORLDS=10000 SAFETY_STUBBORN=2000 SAFETY="backend=ray ray.address=auto".
SAFETY_WORLDS ?= 500
SAFETY_STUBBORN ?= 100
SAFETY ?=
safety: $(STAMP)
	$(BIN)/safety worlds=$(SAFETY_WORLDS) stubborn_worlds=$(SAFETY_STUBBORN) $(SAFETY)

# Every table and figure of the README's Results section from scratch (dataset, 3 trainings per model, held-out batches of
# every gradient source, Table II scenarios, the cooperation sweep, interaction benchmark, step-time bench, the ceiling
# after the batches with their runs as starts): results/README-results.md and
# results/*.png. About 2.75 hours on 2 cores, estimated (one training seed took 49-61 min before the students'
# fine-tune on the interactive step's states, about 5 min more a training); `make results-full` is the preset for a
# bigger machine (or a Ray cluster: `results results_preset=full backend=ray ray.address=auto`).
results: $(STAMP)
	$(BIN)/results results_preset=small

results-full: $(STAMP)
	$(BIN)/results results_preset=full

# Models trained in one world tested in the other, ours (dense) and highway-env's: each world's dataset and models at demo
# size, then in both worlds the ceiling and the planner with cv and each world's student and surrogate (ADMM, and NNMPC
# for the student): results/cross-world.md. About 2 hours on 2 cores; `cross-world models.dense=models data.dense=data/small`
# reuses make demo's models for our world.
cross-world: $(STAMP)
	$(BIN)/cross-world

# Predictors for mpc=interactive (issue 44 point 3): the dataset that asks the step's questions (cut-ins, yields
# followed through, 25-step branches), a teacher fit on 25-step rollouts (the step's horizon), and a student distilled
# from it, in models/interactive/. Drive them with `planner scenario=dense mpc=interactive
# gradients=student models_dir=models/interactive`. About 55 minutes on 2 cores (docs/archive/2026-11-studies.md).
interactive-models: $(STAMP)
	$(BIN)/make-dataset dataset=interactive
	$(BIN)/distill model=teacher dataset=interactive model.epochs=3 models_dir=models/interactive
	$(BIN)/distill model=student dataset=interactive models_dir=models/interactive

# Predictors trained on the world's answers to mpc=interactive's own candidate plans (issue 44 point 3; needs `make
# demo`'s models): the states its closed loop visits with cv and make demo's student on 60 worlds (seeds from 30,000,000,
# clear of every evaluation seed), the world's answers to 6 candidates at each (data/candidates), make demo's teacher
# fine-tuned on them for one epoch, and a student distilled from it, in models/candidates/. Drive them with `planner
# scenario=dense mpc=interactive gradients=student models_dir=models/candidates`. About 25 minutes on 2 cores.
candidate-models: $(STAMP)
	$(BIN)/python -m bench.candidates worlds=60 "drive=[cv,student]" name=candidates
	$(BIN)/distill model=teacher dataset=interactive dataset_dir=data/candidates init_from=models/teacher.ckpt model.epochs=1 model.task.lr=5e-4 models_dir=models/candidates
	$(BIN)/distill model=student dataset=interactive dataset_dir=data/candidates model.epochs=10 models_dir=models/candidates

clean:
	rm -rf outputs multirun mlflow.db mlruns models data/small data/large data/interactive data/candidates results/*/
