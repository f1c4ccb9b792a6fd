"""The host loop: one loop for every kind of run.

A kind of run is a `Job`: offline training on recorded episodes, online training against the
game, PPO, the configurations of a sweep. A job supplies its jitted step on its next inputs,
the fields its steps add to their records, its evaluation and its checkpoints; `host_loop`
owns everything around them, once for all of them:

- the step's metrics come to the host once per step (`jax.device_get`), with the wall-clock
  frames/s of the step;
- the in-graph divergence guard's verdict (`cdrl.training.step.guarded_update`): a lane whose
  step diverged stops, its last good state is checkpointed, and a job that stops on
  divergence (every single run) raises `DivergenceError` naming the step and the parameter
  group;
- training stages (the recurrent baseline's autoencoder, then its LSTM): `Job.stage` at every
  step, which changes the loss weights at a stage's first step;
- when to evaluate (`Plan.eval_every`, and at the end) and when to checkpoint
  (`Plan.checkpoint_every`, and at the end);
- where records go: one `Sink` per lane (a run directory's `metrics.jsonl`, `eval.jsonl` and
  TensorBoard in `cdrl.runs.record_sinks`; a list in memory for `fit`);
- the progress bar.

A lane is one independent run inside the job's program: a sweep trains its configurations as
lanes of one vmapped step; every other job has one lane.
"""
from __future__ import annotations

import dataclasses
import functools
import sys
import time
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from cdrl.models.base import Variant
from cdrl.training.optim import HParams, init_opt_state
from cdrl.training.step import TrainState, init_state, ratio_names, train_step


class DivergenceError(RuntimeError):
    """Training diverged; `state` holds the last good state (before the bad step)."""

    def __init__(self, message: str, state, step: int, group: str, ratio: float):
        super().__init__(message)
        self.state, self.step, self.group, self.ratio = state, step, group, ratio


@dataclasses.dataclass(frozen=True)
class Plan:
    """When a run steps, evaluates and checkpoints: steps `start` .. `steps` - 1; an evaluation
    after every `eval_every` steps (0: none on the way) and, with `final_eval`, one at the end
    (before the last checkpoint) unless the run was already finished; a checkpoint after every
    `checkpoint_every` steps and at the end (0: none)."""

    steps: int
    start: int = 0
    eval_every: int = 0
    checkpoint_every: int = 0
    final_eval: bool = True


@dataclasses.dataclass(frozen=True)
class Divergence:
    """How a lane diverged: the step, the worst watched parameter group and its norm ratio."""

    step: int
    group: str
    ratio: float
    finite: bool
    message: str

    def as_dict(self) -> dict:
        return {"diverged_at": self.step, "diverged_group": self.group, "diverged_ratio": self.ratio,
                "finite": self.finite}


def divergence_of(step: int, metrics: dict, names: list[str], threshold: float) -> Divergence:
    """The `Divergence` of a step whose (host) metrics say `diverged`."""
    group = names[int(metrics["worst_group"])]
    ratio = float(metrics["max_ratio"])
    finite = bool(metrics["finite"])
    why = (f"||grad||/||param|| = {ratio:.3g} exceeds the threshold {threshold:.3g}" if finite
           else "the loss, a gradient or a parameter became NaN/Inf")
    message = (f"training diverged at step {step}: {why}; worst parameter group: {group} "
               f"(ratio {ratio:.3g}). The last good parameters are kept; lower the learning rate.")
    return Divergence(step, group, ratio, finite, message)


def step_record(step: int, metrics: dict, names: list[str], fps: float) -> dict:
    """The record of one step every job writes (`metrics.jsonl`): loss, loss terms, every
    parameter group's norm ratio, the largest watched one, frames/s."""
    return {
        "step": step,
        "loss": float(metrics["loss"]),
        "terms": {k: float(v) for k, v in metrics["terms"].items()},
        "max_ratio": float(metrics["max_ratio"]),
        "worst_group": names[int(metrics["worst_group"])],
        "ratios": dict(zip(names, np.asarray(metrics["ratios"]).tolist())),
        "fps": fps,
    }


class Sink:
    """Where one lane's records go; this one keeps them in memory (`steps`, `evals`)."""

    def __init__(self):
        self.steps: list[dict] = []
        self.evals: list[dict] = []

    def step(self, record: dict) -> None:
        self.steps.append(record)

    def evaluation(self, record: dict, image: np.ndarray | None = None) -> None:
        self.evals.append(record)

    def flush(self) -> None:
        """Called before every checkpoint and at the end: make what was recorded durable."""

    def close(self) -> None:
        self.flush()


class NullSink(Sink):
    """Records nothing (a process that does not write a lane's files, a padding lane)."""

    def step(self, record: dict) -> None:
        pass

    def evaluation(self, record: dict, image: np.ndarray | None = None) -> None:
        pass


class Job:
    """What one kind of run supplies to `host_loop` (see the module docstring). Subclasses set
    `desc`, `frames_per_step`, `ratio_names` and `threshold`, and implement `step`; the other
    hooks default to one lane, no stages, no evaluation and no checkpoints."""

    desc: str = "train"
    lanes: int = 1
    frames_per_step: int = 1
    ratio_names: list[str] = []
    threshold: float = 1e3  # the divergence threshold, for the message
    stop_on_divergence: bool = True  # False: a lane stops, the others go on (a sweep)

    def stage(self, step: int, state, resumed: bool):
        """The state to run step `step` from (a training stage's loss weights and fresh
        momentum at its first step; `resumed`: the run (re)starts at `step`)."""
        return state

    def step(self, state) -> tuple[Any, dict]:
        """One jitted step on the job's next inputs: (state, metrics as arrays)."""
        raise NotImplementedError

    def lane(self, metrics: dict, k: int) -> dict:
        """Lane `k`'s metrics out of the step's (host) metrics."""
        return metrics if self.lanes == 1 else jax.tree.map(lambda x: x[k], metrics)

    def record(self, metrics: dict) -> dict:
        """Fields a lane's step record adds to `step_record`'s (from its host metrics)."""
        return {}

    def evaluate(self, step: int, state, lanes: Sequence[int]) -> dict[int, tuple[dict, np.ndarray | None]]:
        """Evaluations of the live `lanes` after `step` steps: lane -> (record, image or None)."""
        return {}

    def save(self, step: int, state, saves: Sequence[tuple[int, int]], alive: Sequence[bool],
             diverged: dict[int, "Divergence"]) -> str | None:
        """Checkpoint after `step` steps: `saves` lists (lane, step its state is at), the live
        lanes at `step` and the lanes that diverged since the last checkpoint at the step they
        diverged; `alive` and `diverged` (lane -> how) describe every lane. Returns where the
        checkpoints went (for messages), or None."""
        return None

    def postfix(self, records: Sequence[dict]) -> dict:
        """The progress bar's figures from this step's records."""
        return {"loss": f"{np.mean([r['loss'] for r in records]):.4f}", "fps": f"{records[0]['fps']:.0f}"}


@dataclasses.dataclass
class LoopResult:
    """What `host_loop` ends with: the final state, which lanes still train, how the others
    diverged (lane -> `Divergence`), each lane's last evaluation record, and the seconds of
    every step (the first one includes compilation)."""

    state: Any
    alive: list[bool]
    diverged: dict[int, Divergence]
    last_eval: dict[int, dict]
    seconds: list[float]


def host_loop(job: Job, state, plan: Plan, sinks: Sequence[Sink], alive: Sequence[bool] | None = None,
              progress: bool | None = False) -> LoopResult:
    """Run `job` from `state` through `plan`, its records into `sinks` (one per lane); `alive`:
    which lanes train (default all). Raises `DivergenceError` when a job that stops on
    divergence diverges, after checkpointing its last good state and flushing its sinks."""
    if len(sinks) != job.lanes:
        raise ValueError(f"{job.desc}: {job.lanes} lanes but {len(sinks)} sinks")
    alive = [bool(a) for a in (alive if alive is not None else [True] * job.lanes)]
    diverged: dict[int, Divergence] = {}
    frozen: dict[int, int] = {}  # lanes that diverged since the last checkpoint -> their step
    last_eval: dict[int, dict] = {}
    seconds: list[float] = []
    show = sys.stderr.isatty() if progress is None else progress
    bar = tqdm(total=plan.steps, initial=min(plan.start, plan.steps), disable=not show, desc=job.desc, unit="step")

    def evaluate(step: int) -> None:
        for k, (record, image) in job.evaluate(step, state, [k for k in range(job.lanes) if alive[k]]).items():
            sinks[k].evaluation(record, image)
            last_eval[k] = record

    try:
        state = job.stage(plan.start, state, resumed=True)
        t_last = time.perf_counter()
        for step in range(plan.start, plan.steps):
            if step > plan.start:
                state = job.stage(step, state, resumed=False)
            state, metrics = job.step(state)
            metrics = jax.device_get(metrics)
            now = time.perf_counter()
            seconds.append(now - t_last)
            fps, t_last = job.frames_per_step / max(now - t_last, 1e-9), now
            records = []
            for k in range(job.lanes):
                if not alive[k]:
                    continue
                m = job.lane(metrics, k)
                if m["diverged"]:
                    alive[k], frozen[k] = False, step
                    diverged[k] = divergence_of(step, m, job.ratio_names, job.threshold)
                    continue
                records.append({**step_record(step, m, job.ratio_names, fps), **job.record(m)})
                sinks[k].step(records[-1])
            if job.stop_on_divergence and frozen:
                for sink in sinks:
                    sink.flush()
                where = job.save(step, state, sorted(frozen.items()), alive, diverged)
                first = diverged[min(frozen)]
                saved = f" Last good state saved in {where}." if where else ""
                raise DivergenceError(first.message + saved, state, step, first.group, first.ratio)
            done = step + 1
            # The final evaluation comes before the final checkpoint: a run killed between the
            # two resumes from the checkpoint before and evaluates again, while one whose last
            # checkpoint is written has its final evaluation recorded.
            periodic = plan.eval_every and done % plan.eval_every == 0 and done < plan.steps
            if periodic or (plan.final_eval and done == plan.steps):
                evaluate(done)
            if plan.checkpoint_every and (done % plan.checkpoint_every == 0 or done == plan.steps):
                for sink in sinks:
                    sink.flush()
                saves = [(k, done) for k in range(job.lanes) if alive[k]] + sorted(frozen.items())
                job.save(done, state, saves, alive, diverged)
                frozen.clear()
            bar.update(1)
            if records:
                bar.set_postfix(job.postfix(records))
    finally:
        bar.close()
        for sink in sinks:
            sink.flush()
    return LoopResult(state, alive, diverged, last_eval, seconds)


# ---- training stages (the recurrent baseline trains in two)

def stage_schedule(variant: Variant, steps: int) -> list[tuple[int, dict[str, float]]]:
    """(first step, loss weights) of each training stage; empty for single-stage variants,
    which train with the weights of the given `HParams`."""
    if not variant.stages:
        return []
    weights = variant.stage_loss_weights()
    return [(i * steps // len(weights), w) for i, w in enumerate(weights)]


def feed_schedule(curriculum: Sequence[int], steps: int) -> list[tuple[int, int]]:
    """(first step, K) of each part of a multi-step curriculum (`HParams.feed_every`): equal
    parts of `steps`; empty for teacher forcing throughout."""
    if tuple(curriculum) == (1,):
        return []
    return [(i * steps // len(curriculum), int(k)) for i, k in enumerate(curriculum)]


def enter_stage(variant: Variant, schedule, step: int, state: TrainState, hp: HParams, resumed: bool = False):
    """(state, hp) for `step`: at a stage's first step its loss weights, and fresh momentum
    after the first stage. `resumed`: a run (re)starting at `step` also takes the weights of
    the stage it is inside.

    Works on a sweep's stacked state and hyper-parameters too (leading config axis on
    every leaf and on `hp.diverge_threshold`)."""
    shape = jnp.shape(hp.diverge_threshold)
    init = functools.partial(init_opt_state, hp.opt)
    for first, weights in schedule:
        if step == first and first > 0:
            state = state.replace(opt_state=(jax.vmap(init) if shape else init)(state.params))
        if step == first or (resumed and first <= step):
            hp = hp.replace(loss_weights={k: jnp.broadcast_to(jnp.asarray(weights[k], jnp.float32), shape)
                                          for k in hp.loss_weights})
    return state, hp


class TrainJob(Job):
    """Offline TBPTT training of a variant on a chunk stream (`stream.next_chunk()`), with
    its training stages: the in-memory job of `fit`, and the core of `cdrl train`'s offline
    run (which adds evaluation, checkpoints and device layouts)."""

    def __init__(self, variant: Variant, stream, hp: HParams, steps: int, names: list[str],
                 curriculum: Sequence[int] = (1,)):
        self.variant, self.stream, self.hp = variant, stream, hp
        self.schedule = stage_schedule(variant, steps)
        self.feeds = feed_schedule(curriculum, steps)
        self.desc = f"train {variant.name}"
        self.frames_per_step = stream.batch * stream.unroll
        self.ratio_names = names
        self.threshold = float(hp.diverge_threshold)

    def stage(self, step: int, state, resumed: bool):
        staged, self.hp = enter_stage(self.variant, self.schedule, step, state, self.hp, resumed=resumed)
        for first, k in self.feeds:
            if step == first or (resumed and first <= step):
                self.hp = self.hp.replace(feed_every=jnp.asarray(k, jnp.int32))
        return staged

    def inputs(self, chunk):
        """The step's (hyper-parameters, chunk) as the step takes them."""
        return self.hp, chunk

    def run_step(self, state, hp, chunk):
        return train_step(self.variant, state, hp, chunk)

    def step(self, state):
        return self.run_step(state, *self.inputs(self.stream.next_chunk()))


def fit(variant: Variant, stream, steps: int, hp: HParams, key: jax.Array | None = None,
        state: TrainState | None = None, callback=None,
        curriculum: Sequence[int] = (1,)) -> tuple[TrainState, list[dict]]:
    """Train in memory for `steps` chunks of `stream` through the host loop every run uses;
    returns (state, the steps' records). `callback(record)` sees each record as it comes;
    `curriculum`: the multi-step K of each equal part of the steps (`feed_schedule`; `hp`
    must then be `fed`). Raises `DivergenceError` (with the last good state) on divergence."""
    if state is None:
        if key is None:
            raise ValueError("fit needs either a PRNG key or an initial state")
        state = init_state(variant, key, stream.batch, hp)

    class Recorder(Sink):
        def step(self, record):
            super().step(record)
            if callback is not None:
                callback(record)

    sink = Recorder()
    job = TrainJob(variant, stream, hp, steps, ratio_names(state), curriculum=curriculum)
    result = host_loop(job, state, Plan(steps=steps, final_eval=False), [sink])
    return result.state, sink.steps
