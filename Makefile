# `make demo` and `make test` each build .venv from pyproject.toml on a machine with only
# Python 3.11, then run. Everything else is optional.
PYTHON ?= python3.11
VENV := .venv
STAMP := $(VENV)/.installed

.PHONY: demo test install bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --upgrade pip
	$(VENV)/bin/python -m pip install --quiet -e ".[test]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/cdrl train --run-dir runs/demo --data synthetic --lr 1.0 --batch 4 --unroll 16 --steps 300

test: $(STAMP)
	$(VENV)/bin/python -m pytest

bench: $(STAMP)
	$(VENV)/bin/python benchmarks/env_throughput.py --quick

clean:
	rm -rf $(VENV) runs
