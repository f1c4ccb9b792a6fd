# `make demo` and `make test` each build .venv from pyproject.toml on a machine with only
# Python 3.11, then run. Everything else is optional.
PYTHON ?= python3.11
VENV := .venv
STAMP := $(VENV)/.installed

.PHONY: demo test install bench notebooks clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --upgrade pip
	$(VENV)/bin/python -m pip install --quiet -e ".[test,bench]"
	touch $(STAMP)

install: $(STAMP)

# The main job: collect observation data from the built-in game (behaviour switching), train
# the main model (small preset, about 10 minutes on 2 cores), evaluate it and draw the figures.
# A second `make demo` resumes the run (and finds it finished) instead of starting over.
DEMO := runs/demo
demo: $(STAMP)
	if [ -f $(DEMO)/config.json ]; then $(VENV)/bin/cdrl train --resume $(DEMO); \
	else $(VENV)/bin/cdrl train --run-dir $(DEMO) --variant main --preset small --episodes 60 \
		--episode-steps 200 --batch 4 --unroll 32 --lr 0.5 --steps 1500 --eval-every 500; fi
	$(VENV)/bin/cdrl eval $(DEMO)
	$(VENV)/bin/cdrl plot $(DEMO)

test: $(STAMP)
	$(VENV)/bin/python -m pytest

bench: $(STAMP)
	$(VENV)/bin/python benchmarks/env_throughput.py --quick
	$(VENV)/bin/python benchmarks/train_throughput.py --quick

# Re-run the notebooks at the full budget and store their outputs (tens of minutes on 2 cores).
notebooks: $(STAMP)
	for nb in notebooks/0*.ipynb; do CDRL_NOTEBOOK_BUDGET=full $(VENV)/bin/jupyter execute --inplace --timeout=-1 $$nb || exit 1; done

clean:
	rm -rf $(VENV) runs
