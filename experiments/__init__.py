"""The studies run on cdrl, apart from the library: each folder holds a study's scripts, its
results and its LOG.md (question, command, answer). Run a script from the repository root, as a
file or as a module: `.venv/bin/python experiments/controller/study.py --quick` or
`.venv/bin/python -m experiments.controller.study --quick`."""
