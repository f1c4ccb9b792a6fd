"""`train_run`: start or resume the run of a config in a run directory. Controller variants
train online against the game (`cdrl.runs.online`), the others offline on recorded
episodes (`cdrl.runs.offline`)."""
from __future__ import annotations

from pathlib import Path

from cdrl.models import make_variant
from cdrl.runs.config import RunConfig
from cdrl.runs.offline import offline_train_run
from cdrl.runs.online import online_train_run
from cdrl.runs.rundir import RunDir


def train_run(cfg: RunConfig | None, run_dir: str | Path, resume: bool = False, overrides: dict | None = None,
              progress: bool | None = None) -> dict:
    """Train (or resume: the saved config, with `overrides` of the resumable options) the run
    in `run_dir`; returns a summary dict. A diverging run raises a `RuntimeError` naming the
    step and the parameter group, after saving the last good state. The run directory is
    locked for the whole run: a second writer gets `LockedError` naming this process's pid."""
    run = RunDir(run_dir)
    if resume:
        run.config_for(cfg, resume, overrides)  # a missing run is an error before anything is created
    with run.lock():
        cfg = run.config_for(cfg, resume, overrides)
        launch = online_train_run if make_variant(cfg.variant, cfg.arch).has_controller else offline_train_run
        return launch(cfg, run, resume, progress)
