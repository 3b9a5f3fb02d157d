# Two commands for a fresh machine with only python3 and make:
#   make run    the main job: the paper's Fig. 5 reproduction (4 methods x 10 seeds)
#   make test   the test suite
# Both create the virtual environment in .venv on first use from the pinned lock file.

VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
OUT ?= results

.PHONY: run demo test lint bench clean-venv

$(STAMP): pyproject.toml requirements.lock
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade "pip>=24"
	$(PY) -m pip install --quiet -r requirements.lock
	$(PY) -m pip install --quiet --no-deps -e .
	touch $(STAMP)

run: $(STAMP)
	$(VENV)/bin/gpguided reproduce --preset paper --seeds 10 --out $(OUT)/paper

demo: $(STAMP)
	$(VENV)/bin/gpguided demo --out $(OUT)/demo

test: $(STAMP)
	$(PY) -m pytest -q -n 2 tests

lint: $(STAMP)
	$(VENV)/bin/ruff check gpguided_jax experiments tests

bench: $(STAMP)
	$(PY) experiments/bench_env.py

clean-venv:
	rm -rf $(VENV)
