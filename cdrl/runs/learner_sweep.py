"""Sweeps over a learner that plays the game: every configuration of a `Grid` is one lane of
one vmapped, jitted program.

The configurations differ only in traced numbers (`Learner.hp`) and seeds. Each builds its
learner (`cdrl.runs.online.build_learner`); their static halves (model, game, config) must be
equal, and their traced halves are stacked along a leading lane axis. Every lane starts from
the state `cdrl train --seed` starts from, and one jitted `vmap` of `Learner.train_step`
steps all of them. A lane whose step diverges (its metrics' `diverged`, or a non-finite loss)
keeps its last good state and stops while the others go on.

`learner_sweep_run` writes one ordinary run directory per configuration (config.json,
metrics.jsonl, eval.jsonl with the policy played against the references at the end,
checkpoints), and the grid's `results.json` and `results.md`. It writes no `sweep.json`: an
online sweep cannot be resumed as a whole.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import sys
from pathlib import Path
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from cdrl.learners.api import Learner
from cdrl.runs.checkpoint import Checkpoints
from cdrl.runs.config import RunConfig
from cdrl.runs.grid import GRID_FIELDS, Grid, stack, take
from cdrl.runs.online import GameJob, build_learner
from cdrl.runs.record_sinks import RunWriter
from cdrl.runs.rundir import RunDir, atomic_write_text
from cdrl.runs.sources import with_obs_norm
from cdrl.training.loop import Job, LoopResult, Plan, Sink, host_loop
from cdrl.training.monitor import group_names


def _differing(a: RunConfig, b: RunConfig) -> list[str]:
    return [f.name for f in dataclasses.fields(a) if getattr(a, f.name) != getattr(b, f.name)]


def stack_learners(cfgs: Sequence[RunConfig]) -> tuple[Learner, list[Learner]]:
    """(the learners of `cfgs` stacked along a leading lane axis, each learner). ValueError
    naming the options when two configurations build different static halves, or when
    configurations that differ in more than the seed build the same traced numbers."""
    built = [build_learner(c) for c in cfgs]
    first = built[0]
    for cfg, learner in zip(cfgs[1:], built[1:]):
        for part in ("model", "game", "config"):
            if type(learner) is not type(first) or getattr(learner, part) != getattr(first, part):
                raise ValueError(
                    f"learner {first.name!r}: option(s) {', '.join(_differing(cfgs[0], cfg))} change its static "
                    f"{part}, not a traced number; a sweep varies traced numbers only: train them as separate runs")
    traced = [jax.tree.leaves((lrn.hp, lrn.env_params)) for lrn in built]
    for i, cfg in enumerate(cfgs):
        for j in range(i):
            same = all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(traced[i], traced[j]))
            options = [n for n in _differing(cfgs[j], cfg) if n != "seed"]
            if same and options:
                raise ValueError(f"learner {first.name!r} has no traced number for option(s) {', '.join(options)}: "
                                 "its configurations would train the same program")
    return stack(built), built


def init_lanes(built: Sequence[Learner], cfgs: Sequence[RunConfig]):
    """Every lane's initial state, each exactly as a single run of its configuration starts
    (`learner.init(PRNGKey(seed))`), stacked."""
    return stack([lrn.init(jax.random.PRNGKey(c.seed)) for lrn, c in zip(built, cfgs)])


def learner_sweep_step_fn(learner: Learner, states, alive: jax.Array):
    """One train step of every lane of the stacked `learner`; a lane that is not `alive` keeps
    its state, and one whose step diverges (or whose loss is not finite) stops. Returns
    (states, alive, metrics with a lane axis; `diverged` covers the non-finite loss)."""
    new, metrics = jax.vmap(lambda lrn, s: lrn.train_step(s))(learner, states)
    finite = jnp.isfinite(metrics["loss"]) & metrics["finite"]
    metrics = {**metrics, "finite": finite, "diverged": metrics["diverged"] | ~finite}

    def keep(n, o):
        return jnp.where(alive.reshape(alive.shape + (1,) * (n.ndim - 1)), n, o)

    return jax.tree.map(keep, new, states), alive & ~metrics["diverged"], metrics


_donating = jax.jit(learner_sweep_step_fn, donate_argnums=1)
_keeping = jax.jit(learner_sweep_step_fn)


def learner_sweep_step(learner: Learner, states, alive: jax.Array):
    """`learner_sweep_step_fn`, jitted once per static half; the states donated where the
    learner allows it (`Learner.donate_state`)."""
    return (_donating if learner.donate_state else _keeping)(learner, states, alive)


class LearnerSweepJob(Job):
    """The host loop's job of an online sweep: every configuration a lane of
    `learner_sweep_step`. Records, the policy's evaluation and checkpoints are each lane's
    `GameJob`'s (`ckpts` None: no checkpoints)."""

    stop_on_divergence = False

    def __init__(self, cfgs: Sequence[RunConfig], ckpts: Sequence[Checkpoints] | None = None):
        self.cfgs = list(cfgs)
        self.learner, self.built = stack_learners(self.cfgs)
        self.lanes = len(self.cfgs)
        first = self.built[0]
        self.desc = f"sweep {first.name} x{self.lanes}"
        self.frames_per_step = self.cfgs[0].batch * self.cfgs[0].unroll
        self.threshold = float(self.cfgs[0].diverge_threshold)
        self.ckpts = ckpts
        self.games: list[GameJob] = []

    def init(self):
        """The stacked initial states (each lane from its seed) and every lane alive."""
        states = init_lanes(self.built, self.cfgs)
        self.ratio_names = group_names(self.built[0].watched(take(states, 0)))
        self.games = [GameJob(c, lrn, self.ckpts[k] if self.ckpts else None, self.ratio_names)
                      for k, (c, lrn) in enumerate(zip(self.cfgs, self.built))]
        self.alive = jnp.ones((self.lanes,), bool)
        return states, [True] * self.lanes

    def step(self, states):
        states, self.alive, metrics = learner_sweep_step(self.learner, states, self.alive)
        return states, metrics

    def record(self, metrics: dict) -> dict:
        return self.games[0].record(metrics)

    def evaluate(self, step, states, lanes):
        out = {}
        for k in lanes:
            game = self.games[k]
            if k != lanes[0]:
                game.reference_rows = self.games[lanes[0]].reference_rows  # the same held-out games
            out[k] = ({"step": step, "split": "play", "policies": game.play(take(states, k))}, None)
        return out

    def save(self, step, states, saves, alive, diverged):
        if not self.ckpts:
            return None
        for k, at in saves:
            self.ckpts[k].save(at, take(states, k), {"step": at, "config": dataclasses.asdict(self.cfgs[k])})
        return str(self.ckpts[0].directory.parent.parent)

    def postfix(self, records):
        return {"loss": f"{np.mean([r['loss'] for r in records]):.4f}",
                "reward": f"{np.mean([r['reward'] for r in records]):.3f}"}


def check_sweepable(cfg: RunConfig) -> None:
    """ValueError for a learner an online sweep does not cover yet: the thesis's ascent
    (`thesis_ascent`), whose lanes' metrics the host loop cannot read one by one."""
    if cfg.learner == "thesis_ascent":
        raise ValueError("learner 'thesis_ascent' is not covered by online sweeps yet; sweep a learner that keeps a "
                         "replay buffer or ppo, or train its configurations as separate runs")


def run_lanes(cfgs: Sequence[RunConfig], steps: int, sinks: Sequence[Sink] | None = None,
              progress: bool = False) -> LoopResult:
    """`steps` train steps of every configuration of `cfgs` as lanes of one program, recording
    into `sinks` (default: in memory), no evaluation, no checkpoints."""
    job = LearnerSweepJob(cfgs)
    states, alive = job.init()
    sinks = list(sinks) if sinks is not None else [Sink() for _ in cfgs]
    return host_loop(job, states, Plan(steps=steps, final_eval=False), sinks, alive, progress=progress)


def learner_sweep_run(base: RunConfig, grid: Grid, run_dir: str | Path, progress: bool | None = None) -> list[dict]:
    """Train every configuration of `grid` (the other options from `base`, a learner that plays
    the game) as lanes of one program; write a run directory per configuration and the grid's
    table. Returns one row per configuration (see `results.json`)."""
    run_dir = Path(run_dir)
    if base.devices != 1:
        raise ValueError(f"an online sweep runs on one device; got devices {base.devices}")
    check_sweepable(base)
    base = with_obs_norm(base, RunDir(run_dir).data_cache)  # one input normalisation for every lane
    cfgs = grid.configs(base)
    runs = [RunDir(run_dir / grid.name(c)) for c in cfgs]
    with contextlib.ExitStack() as locks:
        for run in [RunDir(run_dir), *runs]:
            locks.enter_context(run.lock())
        job = LearnerSweepJob(cfgs, [run.checkpoints(c.keep_checkpoints) for c, run in zip(cfgs, runs)])
        states, alive = job.init()
        for c, run in zip(cfgs, runs):
            run.write_config(c)
            run.metrics.truncate(0)
            run.evals.truncate(0)
        plan = Plan(steps=base.steps, eval_every=base.eval_every, checkpoint_every=base.checkpoint_every)
        sinks = [RunWriter(run, 0, c.tensorboard) for c, run in zip(cfgs, runs)]
        show = sys.stderr.isatty() if progress is None else progress
        with contextlib.ExitStack() as closing:
            for sink in sinks:
                closing.callback(sink.close)
            result = host_loop(job, states, plan, sinks, alive, progress=show)
            stopped = [k for k in range(len(cfgs)) if not result.alive[k]]
            if stopped:  # a stopped lane's policy is played from its last good state
                result.last_eval.update({k: rec for k, (rec, _) in
                                         job.evaluate(base.steps, result.state, stopped).items()})
                for k in stopped:
                    sinks[k].evaluation(result.last_eval[k])
    rows = [_row(cfgs[k], runs[k], job.games[k].name, result, k) for k in range(len(cfgs))]
    steady = result.seconds[1:] or result.seconds
    frames = len(cfgs) * base.batch * base.unroll
    summary = {"configs": len(cfgs), "learner": base.learner,
               "sweep_fps": float(np.median([frames / max(t, 1e-9) for t in steady])) if steady else None,
               "first_step_seconds": result.seconds[0] if result.seconds else None, "rows": rows}
    atomic_write_text(run_dir / "results.json", json.dumps(summary, indent=2) + "\n")
    atomic_write_text(run_dir / "results.md", format_learner_results(rows) + "\n")
    return rows


def _row(cfg: RunConfig, run: RunDir, policy: str, result: LoopResult, k: int) -> dict:
    """A lane's row: its grid values, where it diverged, its last tenth's mean loss and
    episode return, and its policy's return against the references."""
    d = result.diverged.get(k)
    records = run.metrics.read()
    tail = records[-max(1, len(records) // 10):]
    returns = [r["mean_return"] for r in tail if r.get("mean_return") is not None]
    rows = result.last_eval.get(k, {}).get("policies", {})
    return {"name": run.path.name, "run_dir": str(run.path), "learner": cfg.learner,
            **{f: getattr(cfg, f) for f in GRID_FIELDS},
            "diverged_at": None if d is None else d.step, "diverged_group": None if d is None else d.group,
            "diverged_ratio": None if d is None else d.ratio,
            "final_loss": float(np.mean([r["loss"] for r in tail])) if tail else None,
            "train_return": float(np.mean(returns)) if returns else None,
            "play_return": rows.get(policy, {}).get("mean_return"),
            "play": rows}


def markdown_rows(rows: Sequence[dict], columns: dict[str, str]) -> str:
    """A sweep's rows as a Markdown table: config, lr, momentum, seed and threshold, then
    `columns` (header -> row key, numbers to 4 digits, None as '-'), then the divergence."""
    head = ["config", "lr", "momentum", "seed", "threshold", *columns, "diverged"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def num(v):
        return "-" if v is None else f"{v:.4g}"

    for r in rows:
        div = "-" if r["diverged_at"] is None else f"step {r['diverged_at']} ({r['diverged_group']}, {r['diverged_ratio']:.3g})"
        cells = [r["name"], f"{r['lr']:g}", f"{r['momentum']:g}", str(r["seed"]), f"{r['diverge_threshold']:g}",
                 *(num(r[key]) for key in columns.values()), div]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def format_learner_results(rows: Sequence[dict]) -> str:
    """An online sweep's rows as a Markdown table."""
    return markdown_rows(rows, {"final loss": "final_loss", "train return": "train_return",
                                "play return": "play_return"})
