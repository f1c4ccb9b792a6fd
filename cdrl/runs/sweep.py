"""Hyper-parameter sweeps as one program, and the thesis's learning-rate search.

A sweep trains every configuration of a `Grid` (learning rate x momentum x seed x
divergence threshold) at once: the train step is `vmap`-ed over a leading config axis of
the state, the traced `HParams` and the data (each seed has its own parameter init and
data order, exactly as `cdrl train --seed` would), and jitted once (`cdrl.runs.grid`). A
configuration that diverges keeps its last good state and stops there while the others go on.

`sweep_run` writes one ordinary run directory per configuration (config.json, metrics.jsonl,
eval.jsonl, checkpoints every `checkpoint_every` steps), so `cdrl eval`, `cdrl plot` and
`cdrl train --resume` work on each of them, plus `results.json` and `results.md` for the
whole grid (`cdrl sweep` also draws every loss curve into `curves.png`:
`cdrl.analysis.plots.plot_sweep`). `resume_sweep` (`cdrl sweep --resume DIR`) continues a
killed sweep exactly from its last complete checkpoint (`cdrl.runs.sweepstate`).

A learner that plays the game (`--learner`, a controller variant's or PPO) sweeps through
`cdrl.runs.learner_sweep`: one device, no resume.

`devices` (`cdrl sweep --devices N`, 0: all) lays the config axis over N devices, which may
belong to several processes (`cdrl sweep --distributed`): each process then writes the run
directories of the configurations it holds (config, logs, TensorBoard, the metadata of their
checkpoints) and process 0 the sweep's own files (sweep.json, progress.json, results), from
what the processes gather to it.

`lr_search` is the thesis's procedure (section 4.3.1): start high and lower the rate until
no parameter group's norm ratio ||grad|| / ||param|| exceeds a threshold over a probe
budget, with every candidate probed in parallel.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import sys
from pathlib import Path
from typing import Sequence

import jax
import numpy as np

from cdrl.data.fingerprint import fingerprint
from cdrl.evaluation.metrics import evaluate, prefixed
from cdrl.models import make_variant
from cdrl.models.base import Variant
from cdrl.runs.config import RunConfig
from cdrl.runs.distributed import all_or_none, allgather_json, is_primary, primary_first
from cdrl.runs.grid import (GRID_FIELDS, Grid, SweepJob, held_configs, init_sweep,  # noqa: F401 - public names
                            make_streams, run_grid, stack, sweep_step, sweep_step_fn, take)
from cdrl.runs.learner_sweep import format_learner_results, learner_sweep_run, markdown_rows
from cdrl.runs.rundir import RunDir, atomic_write_text
from cdrl.runs.sources import load_episodes, verify_data, with_data_dims, with_obs_norm
from cdrl.runs.sweepstate import (SWEEP_FILE, SWEEP_KEEP, gather_progress, read_progress, read_sweep,
                                  restore_configs, resume_point, save_configs, write_progress, write_sweep)
from cdrl.runs.tboard import prediction_image
from cdrl.runs.record_sinks import RunWriter
from cdrl.training.loop import NullSink, Plan, Sink, host_loop
from cdrl.training.parallel import ConfigAxis


def _check_grid(variant: Variant) -> None:
    if variant.has_controller:
        raise ValueError(
            f"variant {variant.name!r} trains online against the game; sweeps cover the offline "
            "variants (train controller variants with `cdrl train`, one seed at a time)"
        )


def sweep_run(base: RunConfig, grid: Grid, run_dir: str | Path, progress: bool | None = None) -> list[dict]:
    """Train every configuration of `grid` (the other options from `base`) as one vmapped
    program; write a run directory per configuration and the grid's table and curves.
    Returns one row per configuration (see `results.json`). The sweep directory and every
    configuration's directory are locked while it runs (`RunDir.lock`)."""
    run_dir = Path(run_dir)
    if base.kind != "offline":  # a learner that plays the game: one process, one device
        if (run_dir / "results.json").exists():
            raise FileExistsError(f"{run_dir} already holds a sweep; pick another --run-dir")
        grid.configs(base)
        return learner_sweep_run(base, grid, run_dir, progress)

    def check() -> None:
        if (run_dir / "results.json").exists() or (run_dir / SWEEP_FILE).exists():
            raise FileExistsError(f"{run_dir} already holds a sweep; continue it with `cdrl sweep --resume {run_dir}` "
                                  "or pick another --run-dir")
        _check_grid(make_variant(base.variant, base.arch))
        grid.configs(base)  # every configuration's values are checked (`RunConfig`) before anything is written

    all_or_none(check, "starting the sweep")  # every process checks before any writes
    with _locked(run_dir, grid, base):
        return _sweep_run(base, grid, run_dir, progress, resume=False)


def resume_sweep(run_dir: str | Path, overrides: dict | None = None, progress: bool | None = None,
                 allow_data_change: bool = False) -> list[dict]:
    """Continue the sweep in `run_dir` from its last complete checkpoint (`cdrl sweep
    --resume`): every configuration's state and data cursor from its own run directory, the
    diverged ones stopped; `overrides` may change only the resumable options (`steps`, ...).
    A configuration whose data changed since the sweep began stops the resume before anything
    is written (`RunDir.check_data`), unless `allow_data_change`."""
    run_dir = Path(run_dir)
    base, grid = all_or_none(lambda: read_sweep(run_dir, overrides), "reading the sweep")
    grid = Grid(**{k: tuple(v) for k, v in grid.items()})
    with _locked(run_dir, grid, base):
        return _sweep_run(base, grid, run_dir, progress, resume=True, allow_data_change=allow_data_change)


def _locked(run_dir: Path, grid: Grid, base: RunConfig) -> contextlib.ExitStack:
    """The locks of the sweep directory (process 0) and of the run directory of every
    configuration this process holds."""
    cfgs = grid.configs(base)
    axis = ConfigAxis.create(base.devices, len(cfgs))
    paths = ([run_dir] if is_primary() else []) + [run_dir / grid.name(cfgs[i]) for i in axis.local if i < len(cfgs)]

    def acquire() -> contextlib.ExitStack:
        with contextlib.ExitStack() as locks:
            for path in paths:
                locks.enter_context(RunDir(path).lock())
            return locks.pop_all()

    return all_or_none(acquire, "locking the sweep's directories")


class SweepRunJob(SweepJob):
    """A sweep's job with its run directories: every configuration's held-out evaluations and
    checkpoints in its own directory, and the sweep's `progress.json` after every checkpoint."""

    def __init__(self, variant, cfgs, run_cfgs, streams, steps, axis, runs, ckpts, episodes, diverged: dict):
        super().__init__(variant, cfgs, streams, steps, axis)
        self.run_cfgs, self.runs, self.ckpts, self.episodes = run_cfgs, runs, ckpts, episodes
        self.earlier = diverged  # how the configurations that had diverged before a resume did

    def config(self, k: int) -> int:
        """The configuration of lane `k`."""
        return self.axis.local[k]

    def held_out(self, i: int) -> list:
        test_eps = self.episodes[self.cfgs[i].seed][1]
        return [test_eps[j] for j in range(min(self.cfgs[i].eval_episodes, len(test_eps)))]

    def meta(self, step: int, i: int) -> dict:
        c = self.run_cfgs[i]
        return {"step": step, "config": dataclasses.asdict(c), "stream": self.streams[c.seed].state_dict(),
                "key": np.asarray(jax.random.PRNGKey(c.seed)).tolist()}

    def evaluate(self, step, states, lanes):
        block = self.axis.to_local(states.params)
        out = {}
        for k in lanes:
            params, episodes = take(block, k), self.held_out(self.config(k))
            record = {"step": step, "split": "test", **evaluate(self.variant, params, episodes, self.cfgs[0].unroll)}
            out[k] = (record, prediction_image(self.variant, params, episodes[0]))
        return out

    def divergences(self, diverged: dict) -> dict[int, dict]:
        """Every divergence of this block's configurations, before a resume and since."""
        return {**self.earlier, **{self.config(k): d.as_dict() for k, d in diverged.items()}}

    def save(self, step, states, saves, alive, diverged):
        save_configs(self.ckpts, [(self.config(k), at, self.meta(at, self.config(k))) for k, at in saves],
                     states, self.axis)
        live = {self.config(k): alive[k] for k in range(self.lanes) if self.real[k]}
        every_alive, every_divergence = gather_progress(live, self.divergences(diverged), len(self.cfgs))
        if is_primary():
            write_progress(self.runs[0].path.parent, step, every_alive, every_divergence)
        return None


def _sweep_run(base: RunConfig, grid: Grid, run_dir: Path, progress: bool | None, resume: bool,
               allow_data_change: bool = False) -> list[dict]:
    cfgs = grid.configs(base)
    axis = ConfigAxis.create(base.devices, len(cfgs))
    mine = [i for i in axis.local if i < len(cfgs)]  # the configurations this process holds
    cache = RunDir(run_dir).data_cache

    def prepare():
        episodes = {c.seed: load_episodes(c, cache) for c in cfgs}
        held_seeds = {c.seed for c in held_configs(cfgs, axis)}
        for seed, (train_eps, test_eps) in episodes.items():
            if seed in held_seeds:
                verify_data(base, train_eps, test_eps)
        resolved = base if resume else with_obs_norm(with_data_dims(base, episodes[cfgs[0].seed][0]), cache)
        return episodes, resolved  # one architecture for every seed

    episodes, base = primary_first(prepare, "loading the sweep's data")  # a game's data is collected once
    data = {seed: fingerprint(*pair) for seed, pair in episodes.items()}
    cfgs = grid.configs(base)
    run_cfgs = [dataclasses.replace(c, devices=1) for c in cfgs]  # each configuration trains on one device
    variant = make_variant(base.variant, base.arch)
    runs = [RunDir(run_dir / grid.name(c)) for c in cfgs]
    changed = {i: runs[i].check_data(data[cfgs[i].seed], allow_data_change) if resume else [] for i in mine}
    if is_primary():
        write_sweep(run_dir, base, dataclasses.asdict(grid))
    streams = make_streams(held_configs(cfgs, axis), lambda c: episodes[c.seed][0])
    ckpts = [run.checkpoints(max(SWEEP_KEEP, c.keep_checkpoints), primary=axis.owner(i))
             for i, (c, run) in enumerate(zip(cfgs, runs))]
    done = read_progress(run_dir, len(cfgs)) if resume else {"step": 0, "alive": [True] * len(cfgs), "diverged": {}}
    if done["step"] > 0:  # an older step if a checkpoint it needs is corrupt
        done = resume_point(ckpts, done, range(len(cfgs)) if jax.process_count() > 1 else mine)
    start = int(done["step"])
    job = SweepRunJob(variant, cfgs, run_cfgs, streams, base.steps, axis, runs, ckpts, episodes,
                      {i: d for i, d in done["diverged"].items() if i in mine})
    resumed = None
    if start > 0:
        fresh, _ = init_sweep(variant, job.held)
        restored, cursors = restore_configs(runs, ckpts, cfgs, take(fresh, 0), done, axis)
        block = [restored[i] if i in restored else take(fresh, k) for k, i in enumerate(axis.local)]
        resumed = (stack(block), np.array([i < len(cfgs) and done["alive"][i] for i in axis.local]))
        for seed, cursor in cursors.items():
            if seed in streams:
                streams[seed].load_state_dict(cursor)
    else:
        for i in mine:
            runs[i].metrics.truncate(0)
            runs[i].evals.truncate(0)
    for i in mine:
        runs[i].write_config(run_cfgs[i])
        runs[i].write_data(data[cfgs[i].seed], start, changed[i], fresh=not resume)
    states, alive = job.init(resumed)
    sinks = [RunWriter(runs[i], start, cfgs[i].tensorboard) if i < len(cfgs) else NullSink() for i in axis.local]
    plan = Plan(steps=base.steps, start=start, eval_every=base.eval_every, checkpoint_every=base.checkpoint_every,
                final_eval=False)
    show = (sys.stderr.isatty() if progress is None else progress) and is_primary()
    with contextlib.ExitStack() as closing:
        for sink in sinks:
            closing.callback(sink.close)
        result = host_loop(job, states, plan, sinks, alive, progress=show)
        block = job.local_states(result.state)
        diverged = job.divergences(result.diverged)
        rows = []
        for k, i in enumerate(axis.local):
            if i < len(cfgs):
                rows.append([i, _result_row(variant, run_cfgs[i], runs[i], sinks[k], take(block, k).params,
                                            episodes[cfgs[i].seed], diverged.get(i))])
    rows = [row for _, row in sorted((pair for part in allgather_json(rows) for pair in part), key=lambda p: p[0])]
    if is_primary():
        # The first step compiles; report the steady state.
        steady = result.seconds[1:] or result.seconds
        frames = len(cfgs) * base.batch * base.unroll
        summary = {"configs": len(cfgs), "sweep_fps": float(np.median([frames / max(t, 1e-9) for t in steady]))
                   if steady else None, "rows": rows}
        atomic_write_text(run_dir / "results.json", json.dumps(summary, indent=2) + "\n")
        atomic_write_text(run_dir / "results.md", format_results(rows) + "\n")
    return rows


def _result_row(variant: Variant, cfg: RunConfig, run: RunDir, sink, params, episodes, diverged: dict | None) -> dict:
    """A configuration's row of the sweep's table; its final held-out evaluation goes to
    `sink` (at its last step: the step it diverged at, or the last)."""
    train_eps, test_eps = episodes
    row = {"name": run.path.name, "run_dir": str(run.path),
           **{k: getattr(cfg, k) for k in GRID_FIELDS}, "diverged_at": None}
    row.update(diverged or {})
    losses = run.metrics.read()
    tail = losses[-max(1, len(losses) // 10):]
    row["final_loss"] = float(np.mean([r["terms"].get("obs_bce", r["loss"]) for r in tail])) if tail else None
    row["max_ratio"] = max((r["max_ratio"] for r in losses), default=None)
    n = cfg.eval_episodes
    for split, eps in (("train", [train_eps[j] for j in range(min(n, len(train_eps)))]),
                       ("test", [test_eps[j] for j in range(min(n, len(test_eps)))])):
        scores = evaluate(variant, params, eps, cfg.unroll)
        row.update(prefixed(scores, split))
        if split == "test":
            steps = row["diverged_at"] if row["diverged_at"] is not None else cfg.steps
            sink.evaluation({"step": steps, "split": "test", **scores}, prediction_image(variant, params, eps[0]))
    return row


def format_results(rows: Sequence[dict]) -> str:
    """The sweep's rows as a Markdown table (an online sweep's: `format_learner_results`)."""
    if rows and "learner" in rows[0]:
        return format_learner_results(rows)
    return markdown_rows(rows, {"final train BCE": "final_loss", "test BCE": "test_bce",
                                "copy-last BCE": "test_copy_bce", "entropy floor": "test_target_entropy",
                                "excess ratio": "test_excess_ratio", "max norm ratio": "max_ratio"})


def lr_search(base: RunConfig, candidates: Sequence[float], probe_steps: int, threshold: float,
              progress: bool | None = None, data_cache: str | Path = "runs/data-cache",
              seeds: Sequence[int] = ()) -> dict:
    """The thesis's learning-rate search: probe every candidate rate for `probe_steps` steps
    in one vmapped program; a candidate is rejected as soon as a group's norm ratio exceeds
    `threshold` (or anything becomes non-finite). With `seeds`, every candidate is probed on
    every seed (each its own initialisation and, for game data, its own data set) and passes
    only if it passes on all of them: the rate a sweep over those seeds can train at.
    Returns the highest rate that survives (`chosen`, None if none does) and, per candidate,
    the largest ratio seen on any seed and, for a rejected one, the seed, step and parameter
    group that rejected it first (`per_seed`: each seed's own). Kernels are watched, not
    biases (see `cdrl.training.step.watched_groups`). Game data is cached under `data_cache`."""
    if not candidates or not all(math.isfinite(c) and c > 0 for c in candidates):
        raise ValueError(f"the learning-rate candidates must be finite numbers > 0, got {list(candidates)}")
    candidates = sorted({float(c) for c in candidates}, reverse=True)
    seeds = tuple(int(s) for s in seeds) or (base.seed,)
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"the seeds of a learning-rate search repeat a value: {list(seeds)}")
    if probe_steps < 1:
        raise ValueError(f"probe_steps must be >= 1, got {probe_steps}")
    if not (math.isfinite(threshold) and threshold > 0):
        raise ValueError(f"threshold must be a finite number > 0, got {threshold}")
    _check_grid(make_variant(base.variant, base.arch))
    base = dataclasses.replace(base, steps=probe_steps, diverge_threshold=threshold)
    episodes = {s: load_episodes(dataclasses.replace(base, seed=s), Path(data_cache)) for s in seeds}
    base = with_obs_norm(with_data_dims(dataclasses.replace(base, seed=seeds[0]), episodes[seeds[0]][0]),
                         Path(data_cache))  # one architecture and input normalisation, as in a sweep
    cfgs = Grid(lr=tuple(candidates), seed=seeds).configs(base)
    variant = make_variant(base.variant, base.arch)
    job = SweepJob(variant, cfgs, make_streams(cfgs, lambda c: episodes[c.seed][0]), probe_steps,
                   ConfigAxis.create(base.devices, len(cfgs)))
    job.desc = f"lr-search x{len(cfgs)}"
    states, alive = job.init()
    sinks = [Sink() for _ in range(job.lanes)]
    show = sys.stderr.isatty() if progress is None else progress
    result = host_loop(job, states, Plan(steps=probe_steps, final_eval=False), sinks, alive, progress=show)
    per_config = []
    for k, (cfg, sink) in enumerate(zip(cfgs, sinks)):
        d = result.diverged.get(k)
        largest = max([r["max_ratio"] for r in sink.steps] + ([d.ratio if d.finite else math.inf] if d else []),
                      default=0.0)
        per_config.append({"seed": cfg.seed, "max_ratio": float(largest), "rejected": None if d is None else
                           {"step": d.step, "group": d.group, "ratio": d.ratio, "finite": d.finite, "seed": cfg.seed}})
    results = []
    for lr in candidates:
        runs = [r for cfg, r in zip(cfgs, per_config) if cfg.lr == lr]
        rejections = sorted((r["rejected"] for r in runs if r["rejected"] is not None), key=lambda d: d["step"])
        results.append({"lr": lr, "max_ratio": max(r["max_ratio"] for r in runs),
                        "rejected": rejections[0] if rejections else None, "per_seed": runs})
    passing = [r["lr"] for r in results if r["rejected"] is None]
    return {"chosen": max(passing) if passing else None, "threshold": threshold, "probe_steps": probe_steps,
            "seeds": list(seeds), "candidates": results}
