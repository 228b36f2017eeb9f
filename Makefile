# Two commands on a fresh machine: `make demo` and `make test`. Both create .venv when missing or stale.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench bench-zstep interaction batch ceiling results results-full cross-world interactive-models candidate-models clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]'
	touch $(STAMP)

# The whole pipeline at demo size (about 12 minutes on 2 cores once installed): data, teacher, certified student, the
# student distilled further on the states mpc=interactive visits with cv on 10 dense worlds and the world's answers to
# its candidate plans there (data/small/candidates: 1 minute; seeds from 30,000,000; without it the student's
# interactive step merges courteously in none of 160 tuning worlds, with it in 44%: docs/studies.md), the
# states the student's courteous planner linearises at (seeds from 5,000,000, kept from data and tests), the gradient
# surrogate trained and tested on them, closed-loop ADMM-NNMPC vs NNMPC in both scenarios, the accuracy-vs-speed table;
# then the dense headline (about 1.5 of those minutes, estimated from 144 s of processor time, two thirds of it the
# ceiling's search): on 4 held-out dense worlds (seeds from 2,000,000) the clairvoyant ceiling, ADMM with
# constant-velocity predictions (cv) and the paper's step, then the courteous step, one short table and a GIF of one
# courteous merge (outputs/demo/merge_courteous.gif). cv, because the courteous step merges as often with it as with the
# learned predictors (results/README-results.md) and the student's paper step takes 4.5 times as long there. The teacher
# trains 4 epochs here (2 min) instead of its default 12 (6.5 min: 40.6 against 42.6 mm rollout ADE; `make results` uses
# 12); the surrogate sees 2000 of the planner's states instead of its default 8000.
demo: $(STAMP)
	$(BIN)/make-dataset
	$(BIN)/distill model=teacher model.epochs=4
	$(BIN)/distill model=student
	$(BIN)/python -m bench.candidates worlds=10 "drive=[cv]" out_dir=data/small name=candidates
	$(BIN)/distill model=student dataset=interactive dataset_dir=data/small/candidates init_from=models/student.ckpt model.epochs=10 eval_dir=data/small
	$(BIN)/planner scenario=dense gradients=student mpc=courteous method=admm episodes=8 seed=5000000 plots=false record_dir=data/small/iterates
	$(BIN)/surrogate data.iterates=data/small/iterates data.iterate_states=2000
	$(BIN)/planner --gradients=surrogate method=both scenario=two_lane
	$(BIN)/planner --gradients=surrogate method=both scenario=three_lane
	$(BIN)/planner --gradients=student method=both scenario=two_lane
	$(BIN)/compare
	$(BIN)/ceiling scenario=dense episodes=4 seed=2000000 out_dir=outputs/demo
	$(BIN)/planner scenario=dense gradients=cv method=admm episodes=4 seed=2000000 plots=false out_dir=outputs/demo/paper
	$(BIN)/planner scenario=dense gradients=cv mpc=courteous method=admm episodes=4 seed=2000000 plots=false out_dir=outputs/demo/courteous
	$(BIN)/python -m bench.demo outputs/demo scenario=dense gradients=cv

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest

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
# tuning worlds on a busy machine; docs/studies.md). The same for other scenarios: `ceiling scenario=dense_deadline
# episodes=200`; `backend=ray ray.address=auto` for a cluster; a planner batch's runs as further
# starts: 'starts=["<its out_dir>/steps/admm_{seed}.csv"]' (planner/batch.py writes them; `make results` passes them all).
ceiling: $(STAMP)
	$(BIN)/ceiling scenario=dense episodes=200 seed=2000000

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
# gradients=student models_dir=models/interactive`. About 55 minutes on 2 cores (docs/studies.md).
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
