"""Hyper-parameter sweeps as one program, and the thesis's learning-rate search.

A sweep trains every configuration of a `Grid` (learning rate x momentum x seed x
divergence threshold) at once: the train step is `vmap`-ed over a leading config axis of
the state, the traced `HParams` and the data (each seed has its own parameter init and
data order, exactly as `cdrl train --seed` would), and jitted once. A configuration that
diverges keeps its last good state and stops there while the others go on.

`sweep_run` writes one ordinary run directory per configuration (config.json, metrics.jsonl,
eval.jsonl, checkpoints every `checkpoint_every` steps), so `cdrl eval`, `cdrl plot` and
`cdrl train --resume` work on each of them, plus `results.json` and `results.md` for the
whole grid (`cdrl sweep` also draws every loss curve into `curves.png`:
`cdrl.analysis.plots.plot_sweep`). `resume_sweep` (`cdrl sweep --resume DIR`) continues a
killed sweep exactly from its last complete checkpoint (`cdrl.runs.sweepstate`).
`lr_search` is the thesis's procedure (section 4.3.1): start high and lower the rate until
no parameter group's norm ratio ||grad|| / ||param|| exceeds a threshold over a probe
budget, with every candidate probed in parallel.
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import itertools
import json
import math
import sys
import time
from pathlib import Path
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from cdrl.data.stream import Chunk, ChunkStream
from cdrl.evaluation.metrics import evaluate, prefixed
from cdrl.models import make_variant
from cdrl.models.base import Variant
from cdrl.runs.config import RunConfig
from cdrl.runs.offline import step_record
from cdrl.runs.rundir import RunDir, atomic_write_text
from cdrl.runs.sources import load_episodes, verify_data, with_data_dims, with_obs_norm
from cdrl.runs.sweepstate import (SWEEP_FILE, SWEEP_KEEP, read_progress, read_sweep, restore_configs, write_progress,
                                  write_sweep)
from cdrl.runs.tboard import TBLog
from cdrl.training.loop import enter_stage, stage_schedule
from cdrl.training.monitor import group_names
from cdrl.training.optim import HParams, init_opt_state
from cdrl.training.step import TrainState, init_params, train_step_fn

# The options a sweep may vary: every one is a traced number of the train step (or the seed,
# which sets the initialisation and the data order), so the whole grid is one program.
GRID_FIELDS = ("lr", "momentum", "b2", "weight_decay", "grad_clip", "lr_warmup", "seed", "diverge_threshold")
# Short names in a configuration's directory name; the first four always appear.
_NAME_PARTS = {"lr": "lr", "momentum": "mom", "seed": "seed", "diverge_threshold": "thr", "b2": "b2",
               "weight_decay": "wd", "grad_clip": "clip", "lr_warmup": "warm"}


@dataclasses.dataclass(frozen=True)
class Grid:
    """The values of each swept option (empty: the base config's value); the sweep trains
    their cartesian product."""

    lr: tuple[float, ...] = ()
    momentum: tuple[float, ...] = ()
    b2: tuple[float, ...] = ()
    weight_decay: tuple[float, ...] = ()
    grad_clip: tuple[float, ...] = ()
    lr_warmup: tuple[int, ...] = ()
    seed: tuple[int, ...] = ()
    diverge_threshold: tuple[float, ...] = ()

    def __post_init__(self):
        for name in GRID_FIELDS:
            values = tuple(getattr(self, name))
            if len(set(values)) != len(values):
                raise ValueError(f"the grid repeats a value of {name}: {values}")
            object.__setattr__(self, name, values)

    def configs(self, base: RunConfig) -> list[RunConfig]:
        """One `RunConfig` per grid point, in `itertools.product` order of the fields."""
        axes = [getattr(self, name) or (getattr(base, name),) for name in GRID_FIELDS]
        return [dataclasses.replace(base, **dict(zip(GRID_FIELDS, p))) for p in itertools.product(*axes)]

    def name(self, cfg: RunConfig) -> str:
        """The directory name of `cfg`'s configuration: lr, momentum, seed and threshold, and
        every other option this grid sets."""
        shown = ["lr", "momentum", "seed", "diverge_threshold"] + [
            n for n in GRID_FIELDS if getattr(self, n) and n not in ("lr", "momentum", "seed", "diverge_threshold")]
        return "-".join(f"{_NAME_PARTS[n]}{getattr(cfg, n):g}" for n in shown)


def stack(trees: Sequence) -> object:
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)


def take(tree, i: int):
    """Configuration `i` of a stacked pytree."""
    return jax.tree.map(lambda x: x[i], tree)


def sweep_step_fn(variant: Variant, states: TrainState, hps: HParams, alive: jax.Array, chunks: Chunk):
    """One train step of every configuration; a configuration that is not `alive` (it
    diverged earlier) keeps its state. Returns (states, alive, metrics with a config axis)."""
    new, metrics = jax.vmap(functools.partial(train_step_fn, variant))(states, hps, chunks)

    def keep(n, o):
        return jnp.where(alive.reshape(alive.shape + (1,) * (n.ndim - 1)), n, o)

    states = jax.tree.map(keep, new, states)
    return states, alive & ~metrics["diverged"], metrics


sweep_step = jax.jit(sweep_step_fn, static_argnums=0, donate_argnums=1)


def init_sweep(variant: Variant, cfgs: Sequence[RunConfig]) -> tuple[TrainState, HParams]:
    """Stacked initial states and hyper-parameters, each configuration exactly as
    `cdrl train` would start it (parameters from `PRNGKey(seed)`)."""
    hps = stack([c.hparams(variant) for c in cfgs])
    keys = jnp.stack([jax.random.PRNGKey(c.seed) for c in cfgs])
    params = init_params(variant, keys)
    carry = variant.init_carry(cfgs[0].batch)
    states = TrainState(
        params=params,
        opt_state=jax.vmap(functools.partial(init_opt_state, hps.opt))(params),
        carry=jax.tree.map(lambda x: jnp.broadcast_to(x, (len(cfgs),) + x.shape), carry),
        step=jnp.zeros((len(cfgs),), jnp.int32),
    )
    return states, hps


def _check_grid(variant: Variant) -> None:
    if variant.has_controller:
        raise ValueError(
            f"variant {variant.name!r} trains online against the game; sweeps cover the offline "
            "variants (train controller variants with `cdrl train`, one seed at a time)"
        )


StepCallback = Callable[[int, dict, float, TrainState], None]


def run_grid(variant: Variant, cfgs: Sequence[RunConfig], streams: dict[int, ChunkStream], steps: int,
             callback: StepCallback | None = None, on_diverge: Callable[[int, int, TrainState], None] | None = None,
             start: int = 0, resumed: tuple[TrainState, np.ndarray] | None = None):
    """The host loop of a sweep: `steps` vmapped train steps. `streams` maps each seed to
    its data stream. `callback(step, metrics, seconds, states)` sees every step's metrics
    (numpy, config axis first) and the stacked states after it; `on_diverge(step, i, state_i)` sees the last good state of a
    configuration at the step it diverges. `resumed` (stacked states, alive mask) continues
    a sweep from step `start`. Returns (stacked final states, alive mask)."""
    states, hps = init_sweep(variant, cfgs)
    alive = jnp.ones((len(cfgs),), bool)
    if resumed is not None:
        states, alive = resumed[0], jnp.asarray(resumed[1], bool)
    schedule = stage_schedule(variant, steps)
    states, hps = enter_stage(variant, schedule, start, states, hps, resumed=start > 0)
    for step in range(start, steps):
        if step > start:
            states, hps = enter_stage(variant, schedule, step, states, hps)
        chunk_of = {seed: stream.next_chunk() for seed, stream in streams.items()}
        chunks = jax.tree.map(lambda *xs: np.stack(xs), *[chunk_of[c.seed] for c in cfgs])
        t0 = time.perf_counter()
        was_alive = np.asarray(alive)
        states, alive, metrics = sweep_step(variant, states, hps, alive, chunks)
        metrics = jax.device_get(metrics)
        seconds = time.perf_counter() - t0
        if on_diverge is not None:
            for i in np.flatnonzero(was_alive & np.asarray(metrics["diverged"])):
                on_diverge(step, int(i), take(states, int(i)))
        metrics["alive_before"] = was_alive
        if callback is not None:
            callback(step, metrics, seconds, states)
    return states, np.asarray(alive)


def _streams(cfgs: Sequence[RunConfig], train_eps_of: Callable[[RunConfig], Sequence]) -> dict:
    streams = {}
    for c in cfgs:
        if c.seed not in streams:
            streams[c.seed] = ChunkStream(train_eps_of(c), c.batch, c.unroll, image_size=c.arch.image_size,
                                          action_dim=c.arch.action_dim, seed=c.seed)
    return streams


def sweep_run(base: RunConfig, grid: Grid, run_dir: str | Path, progress: bool | None = None) -> list[dict]:
    """Train every configuration of `grid` (the other options from `base`) as one vmapped
    program; write a run directory per configuration and the grid's table and curves.
    Returns one row per configuration (see `results.json`). The sweep directory and every
    configuration's directory are locked while it runs (`RunDir.lock`)."""
    run_dir = Path(run_dir)
    if (run_dir / "results.json").exists() or (run_dir / SWEEP_FILE).exists():
        raise FileExistsError(f"{run_dir} already holds a sweep; continue it with `cdrl sweep --resume {run_dir}` "
                              "or pick another --run-dir")
    _check_grid(make_variant(base.variant, base.arch))
    with _locked(run_dir, grid, base):
        return _sweep_run(base, grid, run_dir, progress, resume=False)


def resume_sweep(run_dir: str | Path, overrides: dict | None = None, progress: bool | None = None) -> list[dict]:
    """Continue the sweep in `run_dir` from its last complete checkpoint (`cdrl sweep
    --resume`): every configuration's state and data cursor from its own run directory, the
    diverged ones stopped; `overrides` may change only the resumable options (`steps`, ...)."""
    run_dir = Path(run_dir)
    base, grid = read_sweep(run_dir, overrides)
    grid = Grid(**{k: tuple(v) for k, v in grid.items()})
    with _locked(run_dir, grid, base):
        return _sweep_run(base, grid, run_dir, progress, resume=True)


def _locked(run_dir: Path, grid: Grid, base: RunConfig) -> contextlib.ExitStack:
    """The locks of the sweep directory and every configuration's run directory."""
    with contextlib.ExitStack() as locks:
        for path in [run_dir] + [run_dir / grid.name(c) for c in grid.configs(base)]:
            locks.enter_context(RunDir(path).lock())
        return locks.pop_all()


def _sweep_run(base: RunConfig, grid: Grid, run_dir: Path, progress: bool | None, resume: bool) -> list[dict]:
    cfgs = grid.configs(base)
    cache = run_dir.parent / "data-cache"
    episodes = {c.seed: load_episodes(c, cache) for c in cfgs}
    for train_eps, test_eps in episodes.values():
        verify_data(base, train_eps, test_eps)
    if not resume:
        base = with_obs_norm(with_data_dims(base, episodes[cfgs[0].seed][0]), cache)  # one architecture for every seed
    cfgs = grid.configs(base)
    variant = make_variant(base.variant, base.arch)
    write_sweep(run_dir, base, dataclasses.asdict(grid))
    streams = _streams(cfgs, lambda c: episodes[c.seed][0])
    runs = [RunDir(run_dir / grid.name(c)) for c in cfgs]
    ckpts = [run.checkpoints(max(SWEEP_KEEP, c.keep_checkpoints)) for c, run in zip(cfgs, runs)]
    names = group_names(jax.eval_shape(variant.init, jax.random.PRNGKey(0)))
    done = read_progress(run_dir, len(cfgs)) if resume else {"step": 0, "alive": [True] * len(cfgs), "diverged": {}}
    start, diverged = int(done["step"]), done["diverged"]
    resumed = None
    if start > 0:
        fresh, _ = init_sweep(variant, cfgs)
        states, cursors = restore_configs(runs, ckpts, cfgs, [take(fresh, i) for i in range(len(cfgs))], done)
        resumed = (stack(states), np.asarray(done["alive"]))
        for seed, cursor in cursors.items():
            streams[seed].load_state_dict(cursor)
    else:
        for run in runs:
            run.metrics.truncate(0)
            run.evals.truncate(0)
    for c, run in zip(cfgs, runs):
        run.write_config(c)

    def save(step: int, i: int, state: TrainState) -> None:
        c = cfgs[i]
        meta = {"step": step, "config": dataclasses.asdict(c), "stream": streams[c.seed].state_dict(),
                "key": np.asarray(jax.random.PRNGKey(c.seed)).tolist()}
        ckpts[i].save(step, state, meta)

    show = sys.stderr.isatty() if progress is None else progress
    bar = tqdm(total=base.steps, initial=min(start, base.steps), disable=not show,
               desc=f"sweep {base.variant} x{len(cfgs)}", unit="step")
    frames = base.batch * base.unroll
    pending: list[list[dict]] = [[] for _ in cfgs]
    sweep_fps: list[float] = []

    def held_out(i: int) -> list:
        test_eps = episodes[cfgs[i].seed][1]
        return [test_eps[j] for j in range(min(cfgs[i].eval_episodes, len(test_eps)))]

    def callback(step: int, metrics: dict, seconds: float, states: TrainState) -> None:
        sweep_fps.append(len(cfgs) * frames / max(seconds, 1e-9))
        for i in range(len(cfgs)):
            if not metrics["alive_before"][i]:
                continue
            if metrics["diverged"][i]:
                diverged[i] = {"diverged_at": step, "diverged_group": names[int(metrics["worst_group"][i])],
                               "diverged_ratio": float(metrics["max_ratio"][i]),
                               "finite": bool(metrics["finite"][i])}
                continue
            pending[i].append(step_record(step, take(metrics, i), names, frames / max(seconds, 1e-9)))
            tbs[i].step(pending[i][-1])
        done = step + 1
        if base.eval_every and done % base.eval_every == 0 and done < base.steps:
            for i in np.flatnonzero(metrics["alive_before"] & ~metrics["diverged"]):
                params = take(states.params, int(i))
                record = {"step": done, "split": "test", **evaluate(variant, params, held_out(int(i)), cfgs[i].unroll)}
                runs[i].evals.append([record])
                tbs[i].eval(record)
                tbs[i].predictions(done, variant, params, held_out(int(i))[0])
        if done % base.checkpoint_every == 0 or done == base.steps:
            alive = metrics["alive_before"] & ~metrics["diverged"]
            for i, run in enumerate(runs):
                run.metrics.append(pending[i])
                pending[i] = []
                if alive[i]:
                    save(done, i, take(states, i))
                tbs[i].flush()
            write_progress(run_dir, done, alive, diverged)
        bar.update(1)
        bar.set_postfix(loss=f"{float(np.mean(metrics['loss'])):.4f}", fps=f"{sweep_fps[-1]:.0f}")

    tbs = [TBLog(run.tb_dir, start, c.tensorboard) for c, run in zip(cfgs, runs)]
    for tb, run in zip(tbs, runs):
        tb.replay_evals(run.evals.read(), start)
    states, alive = run_grid(variant, cfgs, streams, base.steps, callback, on_diverge=save, start=start,
                             resumed=resumed)
    bar.close()
    rows = []
    for i, (c, run) in enumerate(zip(cfgs, runs)):
        rows.append(_result_row(variant, c, run, take(states, i).params, episodes[c.seed], diverged.get(i)))
        final = run.evals.read()[-1]  # the final held-out evaluation
        tbs[i].eval(final)
        tbs[i].predictions(final["step"], variant, take(states, i).params, held_out(i)[0])
        tbs[i].close()
    # The first step compiles; report the steady state.
    steady = sweep_fps[1:] or sweep_fps
    summary = {"configs": len(cfgs), "sweep_fps": float(np.median(steady)), "rows": rows}
    atomic_write_text(run_dir / "results.json", json.dumps(summary, indent=2) + "\n")
    atomic_write_text(run_dir / "results.md", format_results(rows) + "\n")
    return rows


def _result_row(variant: Variant, cfg: RunConfig, run: RunDir, params, episodes, diverged: dict | None) -> dict:
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
            run.evals.append([{"step": steps, "split": "test", **scores}])
    return row


def format_results(rows: Sequence[dict]) -> str:
    """The sweep's rows as a Markdown table."""
    head = ("| config | lr | momentum | seed | threshold | final train BCE | test BCE | copy-last BCE | entropy floor "
            "| excess ratio | max norm ratio | diverged |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]

    def num(v):
        return "-" if v is None else f"{v:.4g}"

    for r in rows:
        div = "-" if r["diverged_at"] is None else f"step {r['diverged_at']} ({r['diverged_group']}, {r['diverged_ratio']:.3g})"
        lines.append(f"| {r['name']} | {r['lr']:g} | {r['momentum']:g} | {r['seed']} | {r['diverge_threshold']:g} | "
                     f"{num(r['final_loss'])} | {num(r['test_bce'])} | {num(r['test_copy_bce'])} | "
                     f"{num(r['test_target_entropy'])} | {num(r['test_excess_ratio'])} | {num(r['max_ratio'])} | {div} |")
    return "\n".join(lines)


def lr_search(base: RunConfig, candidates: Sequence[float], probe_steps: int, threshold: float,
              progress: bool | None = None, data_cache: str | Path = "runs/data-cache") -> dict:
    """The thesis's learning-rate search: probe every candidate rate for `probe_steps` steps
    in one vmapped program; a candidate is rejected as soon as a group's norm ratio exceeds
    `threshold` (or anything becomes non-finite). Returns the highest rate that survives
    (`chosen`, None if none does) and, per candidate, the largest ratio seen and, for the
    rejected ones, the step and parameter group that rejected them. Kernels are watched,
    not biases (see `cdrl.training.step.watched_groups`). Game data is cached under `data_cache`."""
    candidates = sorted({float(c) for c in candidates}, reverse=True)
    if probe_steps < 1:
        raise ValueError(f"probe_steps must be >= 1, got {probe_steps}")
    if not threshold > 0:
        raise ValueError(f"threshold must be > 0, got {threshold}")
    _check_grid(make_variant(base.variant, base.arch))
    train_eps, _ = load_episodes(base, Path(data_cache))
    base = with_obs_norm(with_data_dims(dataclasses.replace(base, steps=probe_steps, diverge_threshold=threshold),
                                        train_eps), Path(data_cache))
    cfgs = Grid(lr=tuple(candidates)).configs(base)
    variant = make_variant(base.variant, base.arch)
    streams = _streams(cfgs, lambda c: train_eps)
    names = group_names(jax.eval_shape(variant.init, jax.random.PRNGKey(0)))
    largest = np.zeros(len(cfgs))
    rejected: dict[int, dict] = {}
    show = sys.stderr.isatty() if progress is None else progress
    bar = tqdm(total=probe_steps, disable=not show, desc=f"lr-search x{len(cfgs)}", unit="step")

    def callback(step: int, metrics: dict, seconds: float, states: TrainState) -> None:
        for i in range(len(cfgs)):
            if not metrics["alive_before"][i]:
                continue
            ratio = float(metrics["max_ratio"][i])
            largest[i] = max(largest[i], ratio if math.isfinite(ratio) else math.inf)
            if metrics["diverged"][i]:
                rejected[i] = {"step": step, "group": names[int(metrics["worst_group"][i])], "ratio": ratio,
                               "finite": bool(metrics["finite"][i])}
        bar.update(1)

    run_grid(variant, cfgs, streams, probe_steps, callback)
    bar.close()
    results = [{"lr": c.lr, "max_ratio": float(largest[i]), "rejected": rejected.get(i)} for i, c in enumerate(cfgs)]
    passing = [r["lr"] for r in results if r["rejected"] is None]
    return {"chosen": max(passing) if passing else None, "threshold": threshold, "probe_steps": probe_steps,
            "candidates": results}
