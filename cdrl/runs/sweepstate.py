"""A sweep's progress on disk, so that `cdrl sweep --resume DIR` continues it exactly.

    sweep.json      the resolved base config and the grid (written when the sweep starts)
    progress.json   the last step at which every configuration was checkpointed, which
                    configurations were still training then, and how the others diverged

Every `checkpoint_every` steps (and at the last step) the sweep appends each configuration's
metrics, saves each live configuration's checkpoint in its own run directory (state and its
seed's data-stream cursor, all at the same step), and only then rewrites `progress.json`
(atomically). A kill between two configurations' saves leaves `progress.json` at the step
before, whose checkpoints every configuration still has: a sweep keeps at least two
(`SWEEP_KEEP`). A configuration that diverged keeps the checkpoint of its last good state (saved at
the next checkpoint step; the state stays frozen until then) and stays stopped when the sweep
resumes. A checkpoint that fails its checksums (`cdrl.runs.checksums`) makes the resume fall
back to the newest step at which every configuration has a good one (`resume_point`), named
in one line per corrupt checkpoint.

With several processes (`cdrl sweep --distributed`) every checkpoint is a collective orbax
save: orbax writes global arrays only (it refuses arrays that live in one process of several,
and writes numpy arrays from process 0 alone), so each configuration's state is gathered to
every device, the processes write it together, and the process that holds the configuration
writes its metadata. Progress and divergences are gathered to process 0, which alone writes
`progress.json`, after every process's checkpoints are complete.
"""
from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import Sequence

import jax

from cdrl.runs.checkpoint import CheckpointError, Checkpoints, CorruptCheckpointError
from cdrl.runs.config import RESUMABLE, RunConfig, saved_config
from cdrl.runs.distributed import allgather_json
from cdrl.runs.grid import take
from cdrl.runs.rundir import RunDir, atomic_write_text
from cdrl.training.parallel import ConfigAxis, local_copy

SWEEP_FILE = "sweep.json"
PROGRESS_FILE = "progress.json"
SWEEP_KEEP = 2  # checkpoints kept per configuration at least (see the module docstring)


def write_sweep(run_dir: Path, base: RunConfig, grid: dict) -> None:
    atomic_write_text(run_dir / SWEEP_FILE, json.dumps(
        {"base": dataclasses.asdict(base), "grid": grid}, indent=2, allow_nan=False) + "\n")


def read_sweep(run_dir: Path, overrides: dict | None = None) -> tuple[RunConfig, dict]:
    """(base config with `overrides` of the resumable options, grid as a dict) of the sweep in
    `run_dir`. FileNotFoundError / ValueError naming what is missing or refused."""
    path = run_dir / SWEEP_FILE
    if not run_dir.is_dir():
        raise FileNotFoundError(f"sweep directory {run_dir} {'is a file' if run_dir.exists() else 'does not exist'}")
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


def gather_progress(live: dict[int, bool], diverged: dict[int, dict], configs: int) -> tuple[list[bool], dict]:
    """Every process's live mask and divergences of the configurations it holds, merged:
    (which of the `configs` configurations still train, how each diverged one diverged)."""
    alive, every_divergence = [False] * configs, {}
    for part in allgather_json({"live": sorted(live.items()), "diverged": sorted(diverged.items())}):
        for i, is_live in part["live"]:
            alive[int(i)] = bool(is_live)
        every_divergence.update({int(i): d for i, d in part["diverged"]})
    return alive, every_divergence


def save_configs(checkpoints: Sequence[Checkpoints], saves: Sequence[tuple[int, int, dict]], states,
                 axis: ConfigAxis) -> None:
    """Checkpoint the configurations `saves` names (index, step, metadata) of this process's
    block out of the stacked global `states`. With several processes, collective (see the
    module docstring): every process learns which configurations are saved and takes part."""
    if jax.process_count() == 1:
        block = axis.to_local(states)
        for i, step, meta in saves:
            checkpoints[i].save(step, take(block, axis.local.index(i)), meta)
        return
    metas = {i: meta for i, _, meta in saves}
    for i, step in sorted(tuple(pair) for part in allgather_json([[i, step] for i, step, _ in saves]) for pair in part):
        checkpoints[i].save(step, axis.replicated_one(states, i), metas.get(i, {}))


def resume_point(checkpoints: Sequence[Checkpoints], progress: dict, indices: Sequence[int]) -> dict:
    """The progress to resume from: `progress` itself when every configuration of `indices`
    has a good checkpoint to restore (a live one at the progress step, a diverged one its
    newest), else that of the newest earlier checkpoint step at which each has one (a
    configuration that diverged after it trains again from there, and diverges again at the
    same step). Each corrupt checkpoint is named on stderr with the step resumed from.
    `CheckpointError` if there is no such step."""
    step = int(progress["step"])
    diverged_at = {i: int(d["diverged_at"]) for i, d in progress["diverged"].items()}
    listed = {i: checkpoints[i].steps() for i in indices}
    verdicts: dict[tuple[int, int], bool] = {}
    warnings: list[str] = []

    def good(i: int, at: int) -> bool:
        if at not in listed[i]:
            return False
        if (i, at) not in verdicts:
            try:
                checkpoints[i].verify(at)
                verdicts[i, at] = True
            except CorruptCheckpointError as exc:
                warnings.append(str(exc))
                verdicts[i, at] = False
        return verdicts[i, at]

    def usable(i: int, at: int) -> bool:
        if progress["alive"][i] or diverged_at.get(i, at) >= at:  # it trained at `at`
            return good(i, at)
        return bool(listed[i]) and good(i, max(listed[i]))  # its frozen last good state

    for at in sorted({at for i in indices for at in listed[i] if at <= step} | {step}, reverse=True):
        if all(usable(i, at) for i in indices):
            break
    else:
        raise CheckpointError("no step at which every configuration of the sweep has a good checkpoint:\n  "
                              + "\n  ".join(warnings or ["(none listed)"]))
    for warning in warnings if jax.process_index() == 0 else ():
        print(f"warning: {warning}; the sweep resumes from step {at}, where every configuration has a good "
              "checkpoint", file=sys.stderr)
    if at == step:
        return progress
    return {"step": at, "alive": [a or diverged_at.get(i, at) >= at for i, a in enumerate(progress["alive"])],
            "diverged": {i: d for i, d in progress["diverged"].items() if diverged_at[i] < at}}


def restore_configs(runs: Sequence[RunDir], checkpoints: Sequence[Checkpoints], cfgs: Sequence[RunConfig],
                    like, progress: dict, axis: ConfigAxis) -> tuple[dict[int, object], dict[int, dict]]:
    """Each configuration's state from its own run directory: a live one's checkpoint at the
    progress step, a diverged one's last good state (its newest checkpoint). `like` is one
    configuration's state. Returns the states of the configurations this process holds (by
    index) and, per seed, the data-stream cursor (from a live configuration of that seed
    where there is one). Their logs are cut back to the progress step. With several processes
    every process restores every configuration (a restore of global arrays is collective)."""
    step = int(progress["step"])
    several = jax.process_count() > 1
    if several:
        replicated = jax.sharding.NamedSharding(axis.mesh, jax.sharding.PartitionSpec())
        like = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=replicated), like)
    mine = {i for i in axis.local if i < len(cfgs)}
    states, cursors, spare = {}, {}, {}
    for i, (run, ckpts, cfg) in enumerate(zip(runs, checkpoints, cfgs)):
        if i not in mine and not several:
            continue
        steps = ckpts.steps()
        alive = progress["alive"][i]
        if alive and step not in steps:
            raise CheckpointError(f"{ckpts.directory} lacks checkpoint {step}, the step every configuration of "
                                  f"the sweep reached; it has {steps}")
        if not alive and not steps:
            raise CheckpointError(f"{ckpts.directory} holds no checkpoint of the diverged configuration")
        state, meta = ckpts.restore(step if alive else max(steps), like)
        (cursors if alive else spare).setdefault(cfg.seed, meta["stream"])
        if i in mine:
            states[i] = local_copy(state) if several else state
            run.metrics.truncate(step)
            run.evals.truncate(step + 1)
    return states, {**spare, **cursors}
