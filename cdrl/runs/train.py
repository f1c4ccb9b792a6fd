"""`train_run`: start or resume the run of a config in a run directory. A learner that plays
the game (`cdrl.learners`) trains online against it (`cdrl.runs.online`), the others offline on recorded
episodes (`cdrl.runs.offline`), on one device or data parallel over several, which may belong
to several processes (`cdrl train --distributed`: process 0 holds the lock and writes the
run's files)."""
from __future__ import annotations

import contextlib
from pathlib import Path

from cdrl.runs.config import RunConfig
from cdrl.runs.distributed import all_or_none, is_primary
from cdrl.runs.init_from import source_of
from cdrl.runs.offline import offline_train_run
from cdrl.runs.online import online_train_run
from cdrl.runs.rundir import RunDir


def train_run(cfg: RunConfig | None, run_dir: str | Path, resume: bool = False, overrides: dict | None = None,
              progress: bool | None = None, allow_data_change: bool = False) -> dict:
    """Train (or resume: the saved config, with `overrides` of the resumable options) the run
    in `run_dir`; returns a summary dict. A resume whose data set changed since the run began
    raises `DataChangedError` naming the change, unless `allow_data_change` (recorded in the
    run's data.json). A diverging run raises a `RuntimeError` naming the
    step and the parameter group, after saving the last good state. The run directory is
    locked for the whole run: a second writer gets `LockedError` naming this process's pid."""
    run = RunDir(run_dir)
    if resume:  # a missing run is an error before anything is created
        all_or_none(lambda: run.config_for(cfg, resume, overrides), "checking the run")

    def lock() -> contextlib.ExitStack:
        held = contextlib.ExitStack()
        if is_primary():
            held.enter_context(run.lock())
        return held

    with all_or_none(lock, "locking the run directory"):  # every process knows before any writes
        resolved = all_or_none(lambda: run.config_for(cfg, resume, overrides), "reading the run's config")
        if resolved.kind != "offline" and resolved.devices != 1:
            raise ValueError(f"devices={resolved.devices}: learners that play the game train on one device "
                             "(data-parallel training covers the offline variants); use --devices 1")
        source = None if resume else source_of(resolved)
        if source is not None:
            resolved = source[0]
        runs = {"offline": offline_train_run, "online": online_train_run, "model_free": online_train_run}
        return runs[resolved.kind](resolved, run, resume, progress, allow_data_change,
                                   init_params=None if source is None else source[1])
