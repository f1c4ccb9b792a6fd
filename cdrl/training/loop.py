"""The host loop: feeds chunks to the pure train step, watches for divergence, reports.

Everything numeric happens in `cdrl.training.step.train_step`; this loop only moves data, logs and
stops. Variants trained in stages (the recurrent baseline: autoencoder, then LSTM on frozen
codes) get each stage's loss weights in turn, with fresh optimiser momentum at the switch.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from cdrl.data.stream import ChunkStream
from cdrl.models.base import Variant
from cdrl.training.optim import HParams, init_opt_state
from cdrl.training.step import TrainState, init_state, ratio_names, train_step


class DivergenceError(RuntimeError):
    """Training diverged; `state` holds the last good parameters (before the bad step)."""

    def __init__(self, message: str, state: TrainState, step: int, group: str, ratio: float):
        super().__init__(message)
        self.state, self.step, self.group, self.ratio = state, step, group, ratio


@dataclasses.dataclass
class StepRecord:
    """Host-side copy of one step's metrics."""

    step: int
    loss: float
    terms: dict[str, float]
    max_ratio: float
    worst_group: str
    ratios: np.ndarray


def stage_schedule(variant: Variant, steps: int) -> list[tuple[int, dict[str, float]]]:
    """(first step, loss weights) of each training stage; empty for single-stage variants,
    which train with the weights of the given `HParams`."""
    stages = getattr(variant, "stage_loss_weights", None)
    if stages is None:
        return []
    weights = stages()
    return [(i * steps // len(weights), w) for i, w in enumerate(weights)]


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


def divergence_message(record_step: int, metrics: dict, names: list[str], threshold: float) -> tuple[str, str, float]:
    group = names[int(metrics["worst_group"])]
    ratio = float(metrics["max_ratio"])
    if not bool(metrics["finite"]):
        why = "the loss, a gradient or a parameter became NaN/Inf"
    else:
        why = f"||grad||/||param|| = {ratio:.3g} exceeds the threshold {threshold:.3g}"
    message = (
        f"training diverged at step {record_step}: {why}; worst parameter group: {group} "
        f"(ratio {ratio:.3g}). The last good parameters are kept; lower the learning rate."
    )
    return message, group, ratio


def fit(
    variant: Variant,
    stream: ChunkStream,
    steps: int,
    hp: HParams,
    key: jax.Array | None = None,
    state: TrainState | None = None,
    callback: Callable[[StepRecord], None] | None = None,
) -> tuple[TrainState, list[StepRecord]]:
    """Train for `steps` chunks; raises `DivergenceError` (with the last good state) on divergence."""
    if state is None:
        if key is None:
            raise ValueError("fit needs either a PRNG key or an initial state")
        state = init_state(variant, key, stream.batch, hp)
    names = ratio_names(state)
    schedule = stage_schedule(variant, steps)
    history: list[StepRecord] = []
    for i in range(steps):
        state, hp = enter_stage(variant, schedule, i, state, hp)
        state, metrics = train_step(variant, state, hp, stream.next_chunk())
        metrics = jax.device_get(metrics)
        if metrics["diverged"]:
            message, group, ratio = divergence_message(i, metrics, names, float(hp.diverge_threshold))
            raise DivergenceError(message, state, i, group, ratio)
        record = StepRecord(
            step=i,
            loss=float(metrics["loss"]),
            terms={k: float(v) for k, v in metrics["terms"].items()},
            max_ratio=float(metrics["max_ratio"]),
            worst_group=names[int(metrics["worst_group"])],
            ratios=np.asarray(metrics["ratios"]),
        )
        history.append(record)
        if callback is not None:
            callback(record)
    return state, history
