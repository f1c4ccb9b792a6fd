# `make demo` and `make test` each build .venv from pyproject.toml on a machine with only
# Python 3.11, then run. Everything else is optional.
PYTHON ?= python3.11
VENV := .venv
STAMP := $(VENV)/.installed

.PHONY: demo test test-e2e install bench notebooks clean

$(STAMP): pyproject.toml setup.py csrc/onednn_conv.cc
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --upgrade pip
	$(VENV)/bin/python -m pip install --quiet -e ".[test,bench]"
	touch $(STAMP)

install: $(STAMP)

# The main job: collect observation data from the built-in game (behaviour switching), train
# the thesis-sized main model with the default recipe (fast), evaluate it and draw the figures,
# about 10 minutes on 2 cores. A second `make demo` resumes the run (and finds it finished).
DEMO := runs/demo
demo: $(STAMP)
	if [ -f $(DEMO)/config.json ]; then $(VENV)/bin/cdrl train --resume $(DEMO); \
	else $(VENV)/bin/cdrl train --run-dir $(DEMO) --variant main --preset thesis --episodes 60 \
		--episode-steps 200 --steps 1000 --eval-every 250 --checkpoint-every 250; fi
	$(VENV)/bin/cdrl eval $(DEMO)
	$(VENV)/bin/cdrl plot $(DEMO)

# Two workers, a test file each at a time (a file's module fixtures are built once); the
# tests that pin numbers then run compiled at XLA's default optimisation level, as users run.
# `make test` leaves out the end-to-end tier (`e2e`: notebooks executed in a kernel, two-process
# jax.distributed runs, processes killed mid-write), which `make test-e2e` runs; CI runs both
# (.ci/run), sharing one compilation cache (CDRL_TEST_XLA_CACHE).
PYTEST := $(VENV)/bin/python -m pytest -n 2 --dist loadfile --durations=15
test: $(STAMP)
	$(PYTEST) -m "not default_opt and not e2e"
	CDRL_TEST_XLA_OPT=default $(PYTEST) -m "default_opt and not e2e"

test-e2e: $(STAMP)
	$(PYTEST) -m e2e

bench: $(STAMP)
	$(VENV)/bin/python benchmarks/env_throughput.py --quick
	$(VENV)/bin/python benchmarks/train_throughput.py --quick

# Re-run the notebooks at the full budget and store their outputs (about an hour on 2 cores;
# 02 and 03 reuse finished sweeps and runs under notebooks/runs/full/).
notebooks: $(STAMP)
	for nb in notebooks/0*.ipynb; do CDRL_NOTEBOOK_BUDGET=full $(VENV)/bin/jupyter execute --inplace --timeout=-1 $$nb || exit 1; done

clean:
	rm -rf $(VENV) runs
