# Two commands for a fresh machine with only python3 and make:
#   make run    the main job: the paper's Fig. 5 reproduction (4 methods x 100 seeds, float64)
#   make test   the fast tests (make test-all: every test, as CI runs them)
# make results regenerates the result files of the documentation's tables (docs/results/), make
# figures the figures', and each study has its own target: make swingup, make standard, make
# exploration and make model; make notebooks executes the notebooks into the site's pages
# (docs/notebooks/); make docs builds the documentation site into site/.
# Every target creates the virtual environment in .venv on first use from the pinned lock file.

VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
OUT ?= results

SEEDS ?= 100
SEED_START ?= 1000
CONSISTENCY_SEEDS := $(shell seq $(SEED_START) $$(($(SEED_START) + 9)))

.PHONY: run results figures swingup standard exploration model demo test test-all lint bench docs \
	notebooks clean-venv

$(STAMP): pyproject.toml requirements.lock
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade "pip>=24"
	# the lock pins every package, dependencies included: no resolver (pip check verifies it), and
	# modules are byte-compiled when first imported rather than all at install
	$(PY) -m pip install --quiet --no-deps --no-compile -r requirements.lock
	$(PY) -m pip install --quiet --no-deps -e .
	$(PY) -m pip check
	touch $(STAMP)

run: $(STAMP)
	$(VENV)/bin/gpguided reproduce --preset paper --seeds $(SEEDS) --seed-start $(SEED_START) --out $(OUT)/paper

# The Fig. 5, failure and consistency tables: both dtypes on the reported seeds (never used for
# tuning), the batch-vs-alone and float32-vs-float64 comparison, then the documentation's tables.
# It starts afresh: a checkpoint or kernels file left by an earlier run would be resumed, whatever
# code wrote it (the checkpoint's digest covers the config and seeds, not the code).
results: $(STAMP)
	rm -f docs/results/paper_float64/checkpoint_* docs/results/paper_float64/kernels*.npz docs/results/paper_float32/checkpoint_* docs/results/paper_float32/kernels*.npz
	$(VENV)/bin/gpguided reproduce --preset paper --seeds $(SEEDS) --seed-start $(SEED_START) --dtype float64 --out docs/results/paper_float64
	$(VENV)/bin/gpguided reproduce --preset paper --seeds $(SEEDS) --seed-start $(SEED_START) --dtype float32 --out docs/results/paper_float32
	$(PY) experiments/consistency.py --seeds $(CONSISTENCY_SEEDS) --f64 docs/results/paper_float64 --f32 docs/results/paper_float32 --out docs/results/consistency
	$(PY) experiments/docs_tables.py --write

# Figs. 1, 2 and 4, coverage, the two exploratory sweeps (docs/figures/) and the gradient check.
FIGTMP := results/figures-tmp
figures: $(STAMP)
	$(PY) experiments/fig2_fig4_coverage.py --preset paper --seeds 5 --seed-start 1000 --out $(FIGTMP)/fig24
	cp $(FIGTMP)/fig24/fig2_variance.png $(FIGTMP)/fig24/fig4_value.png $(FIGTMP)/fig24/coverage.png $(FIGTMP)/fig24/coverage.json docs/figures/
	$(VENV)/bin/gpguided sweep --param lambda --values 0 10 100 400 1000 --method gp_pg --preset paper --seeds 10 --seed-start 1000 --out $(FIGTMP)/lambda
	cp $(FIGTMP)/lambda/sweep.csv docs/figures/sweep_age_penalty.csv
	cp $(FIGTMP)/lambda/sweep_age_penalty.png docs/figures/
	$(VENV)/bin/gpguided sweep --param beta --values 1 3 10 30 100 --method guided_direction --preset paper --seeds 10 --seed-start 1000 --out $(FIGTMP)/beta
	cp $(FIGTMP)/beta/sweep.csv docs/figures/sweep_inverse_temperature.csv
	cp $(FIGTMP)/beta/sweep_inverse_temperature.png docs/figures/
	$(PY) experiments/fig1_bv_composition.py --out docs/figures
	$(PY) experiments/gradient_check.py --out docs/results/gradient_check.json
	$(PY) experiments/docs_tables.py --write

# The swing-up study (the protocol of gpguided_jax/study.py): tuning on seeds 100-101, then seeds
# 1000-1009 against PPO and SAC, each method's run in methods/<method>/. It starts afresh, as
# `results` does (a held-out checkpoint would be resumed, and its wall time lost).
swingup: $(STAMP)
	rm -f docs/results/swingup/methods/*/checkpoint_* docs/results/swingup/methods/*/kernels*.npz
	$(PY) experiments/swingup_study.py tune
	$(PY) experiments/swingup_study.py heldout
	$(PY) experiments/swingup_study.py gpfig
	$(PY) experiments/swingup_diagnostics.py warm sac
	$(PY) experiments/swingup_diagnostics.py warm --warm-lr 0.003
	$(PY) experiments/docs_tables.py --write

# The standard tasks (docs/standard_tasks.md): tuning on seeds 100-101, then seeds 1000-1009,
# for each task with a comparison on the page. The held-out stage resumes: a method or baseline
# whose heldout/<name>.json holds the same seeds and settings is not run again.
STANDARD_TASKS ?= pendulum-v1 mountaincar-continuous
standard: $(STAMP)
	for t in $(STANDARD_TASKS); do \
	  $(PY) experiments/standard_tasks.py tune --task $$t && \
	  $(PY) experiments/standard_tasks.py heldout --task $$t && \
	  $(PY) experiments/standard_tasks.py report --task $$t || exit 1; \
	done
	$(PY) experiments/docs_tables.py --write

# The exploration study on the swing-up preset: reach, tuning on seeds 100-101, then seeds
# 1000-1019 with every scheme per method; then MountainCarContinuous-v0 and Pendulum-v1 with
# every scheme per method (it resumes: a run recorded with the same settings is not run again;
# remove docs/results/exploration to start afresh).
exploration: $(STAMP)
	$(PY) experiments/exploration_study.py reach
	$(PY) experiments/exploration_study.py tune
	$(PY) experiments/exploration_study.py heldout
	$(PY) experiments/exploration_study.py baselines-tune
	$(PY) experiments/exploration_study.py baselines
	$(PY) experiments/exploration_study.py report
	$(PY) experiments/exploration_study.py standard-tune --task mountaincar-continuous
	$(PY) experiments/exploration_study.py standard --task mountaincar-continuous
	$(PY) experiments/exploration_study.py standard-tune --task pendulum-v1
	$(PY) experiments/exploration_study.py standard --task pendulum-v1
	$(PY) experiments/docs_tables.py --write

# The GP-model study (docs/model_based.md): tuning on seeds 100-101, then the held-out seeds under
# each of the model's exploration choices for each task of MODEL_TASKS, and with the reward learnt
# by the model (under Thompson sampling, the choice its tuning made there) for each of
# MODEL_LEARNED; then each task's table and figure. It resumes, as `standard` does: a tuning
# configuration in tuning_runs.json, or a held-out run whose heldout/<name>.json holds the same
# seeds and settings, is not run again.
MODEL_TASKS ?= pendulum-v1 mountaincar-continuous inverted-pendulum inverted-double-pendulum swingup
MODEL_LEARNED ?= pendulum-v1 mountaincar-continuous swingup
model: $(STAMP)
	for t in $(MODEL_TASKS); do \
	  $(PY) experiments/model_study.py tune --task $$t && \
	  $(PY) experiments/model_study.py heldout --task $$t || exit 1; \
	done
	for t in $(MODEL_LEARNED); do \
	  $(PY) experiments/model_study.py heldout --task $$t --only thompson --reward learned || exit 1; \
	done
	for t in $(MODEL_TASKS); do $(PY) experiments/model_study.py report --task $$t || exit 1; done
	$(PY) experiments/docs_tables.py --write

demo: $(STAMP)
	$(VENV)/bin/gpguided demo --out $(OUT)/demo

# Bytecode is written on first import even where PYTHONDONTWRITEBYTECODE is set: the suite starts
# many Python processes (its subprocesses, notebook kernels), and without it each one compiled
# jax, brax and scipy from source again.
# test leaves out the tests marked slow (the long ones: tests/conftest.py), so that a change is
# checked in a few minutes; test-all runs them all.
test: $(STAMP)
	PYTHONDONTWRITEBYTECODE= $(PY) -m pytest -q -n 2 --dist loadgroup --durations=15 -m "not slow" tests

test-all: $(STAMP)
	PYTHONDONTWRITEBYTECODE= $(PY) -m pytest -q -n 2 --dist loadgroup --durations=15 tests

lint: $(STAMP)
	$(VENV)/bin/ruff check gpguided_jax experiments tests

bench: $(STAMP)
	$(VENV)/bin/gpguided bench --out docs/results/bench.json
	$(PY) experiments/docs_tables.py --write

# The notebooks executed at full size, each written as a page of the site with its outputs
# (docs/notebooks/<name>.md and its figures; experiments/render_notebooks.py). The pages are kept
# in the repository, so that `make docs` only reads them; tests/test_notebooks.py checks that each
# shows its notebook's current cells.
notebooks: $(STAMP)
	$(PY) experiments/render_notebooks.py

# The documentation site (mkdocs.yml, docs/), warnings as errors, into site/.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --site-dir site

clean-venv:
	rm -rf $(VENV)
