"""A sweep's progress on disk, so that `cdrl sweep --resume DIR` continues it exactly.

    sweep.json      the resolved base config and the grid (written when the sweep starts)
    progress.json   the last step at which every configuration was checkpointed, which
                    configurations were still training then, and how the others diverged

Every `checkpoint_every` steps (and at the last step) the sweep appends each configuration's
metrics, saves each live configuration's checkpoint in its own run directory (state and its
seed's data-stream cursor, all at the same step), and only then rewrites `progress.json`
(atomically). A kill between two configurations' saves leaves `progress.json` at the step
before, whose checkpoints every configuration still has: a sweep keeps at least two
(`SWEEP_KEEP`). A configuration that diverged keeps the checkpoint of its last good state
and stays stopped when the sweep resumes.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Sequence

from cdrl.runs.checkpoint import CheckpointError, Checkpoints
from cdrl.runs.config import RESUMABLE, RunConfig, saved_config
from cdrl.runs.rundir import RunDir, atomic_write_text

SWEEP_FILE = "sweep.json"
PROGRESS_FILE = "progress.json"
SWEEP_KEEP = 2  # checkpoints kept per configuration at least (see the module docstring)


def write_sweep(run_dir: Path, base: RunConfig, grid: dict) -> None:
    atomic_write_text(run_dir / SWEEP_FILE, json.dumps(
        {"base": dataclasses.asdict(base), "grid": grid}, indent=2) + "\n")


def read_sweep(run_dir: Path, overrides: dict | None = None) -> tuple[RunConfig, dict]:
    """(base config with `overrides` of the resumable options, grid as a dict) of the sweep in
    `run_dir`. FileNotFoundError / ValueError naming what is missing or refused."""
    path = run_dir / SWEEP_FILE
    if not run_dir.is_dir():
        raise FileNotFoundError(f"sweep directory {run_dir} does not exist")
    if not path.is_file():
        raise ValueError(f"{run_dir} is not a sweep directory: it has no {SWEEP_FILE} (start one with `cdrl sweep`)")
    try:
        saved = json.loads(path.read_text())
        base = saved_config(saved["base"])
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise ValueError(f"{path} is not a valid sweep description: {exc}") from None
    refused = sorted(set(overrides or {}) - RESUMABLE)
    if refused:
        raise ValueError(f"a resumed sweep keeps its configurations: {', '.join('--' + n.replace('_', '-') for n in refused)} "
                         f"cannot change (only {', '.join(sorted(RESUMABLE))} can)")
    return RunConfig(**{**dataclasses.asdict(base), **(overrides or {})}), saved["grid"]


def write_progress(run_dir: Path, step: int, alive: Sequence[bool], diverged: dict[int, dict]) -> None:
    atomic_write_text(run_dir / PROGRESS_FILE, json.dumps(
        {"step": int(step), "alive": [bool(a) for a in alive],
         "diverged": {str(i): d for i, d in sorted(diverged.items())}}, indent=1) + "\n")


def read_progress(run_dir: Path, configs: int) -> dict:
    """The sweep's last complete checkpoint step, live mask and divergences (step 0, all
    live, none when it never reached a checkpoint)."""
    path = run_dir / PROGRESS_FILE
    if not path.is_file():
        return {"step": 0, "alive": [True] * configs, "diverged": {}}
    progress = json.loads(path.read_text())
    if len(progress["alive"]) != configs:
        raise ValueError(f"{path} describes {len(progress['alive'])} configurations, the sweep has {configs}")
    progress["diverged"] = {int(i): d for i, d in progress["diverged"].items()}
    return progress


def restore_configs(runs: Sequence[RunDir], checkpoints: Sequence[Checkpoints], cfgs: Sequence[RunConfig],
                    likes: Sequence, progress: dict) -> tuple[list, dict[int, dict]]:
    """Each configuration's state from its own run directory: a live one's checkpoint at the
    progress step, a diverged one's last good state (its newest checkpoint). Returns the
    states and, per seed, the data-stream cursor (from a live configuration of that seed
    where there is one). The logs are cut back to the progress step."""
    step = int(progress["step"])
    states, cursors, spare = [], {}, {}
    for i, (run, ckpts, cfg, like) in enumerate(zip(runs, checkpoints, cfgs, likes)):
        steps = ckpts.steps()
        alive = progress["alive"][i]
        if alive and step not in steps:
            raise CheckpointError(f"{ckpts.directory} lacks checkpoint {step}, the step every configuration of "
                                  f"the sweep reached; it has {steps}")
        if not alive and not steps:
            raise CheckpointError(f"{ckpts.directory} holds no checkpoint of the diverged configuration")
        state, meta = ckpts.restore(step if alive else max(steps), like)
        states.append(state)
        (cursors if alive else spare).setdefault(cfg.seed, meta["stream"])
        run.metrics.truncate(step)
        run.evals.truncate(step + 1)
    return states, {**spare, **cursors}
