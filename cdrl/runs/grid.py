"""A grid of configurations trained as one program: the grid, the stacked train step, and its
job for the host loop (`cdrl.runs.sweep` adds the run directories, `cdrl.runs.sweepstate` the
checkpoints).

The train step is `vmap`-ed over a leading config axis of the state, the traced `HParams` and
the data (each seed has its own parameter init and data order, exactly as `cdrl train --seed`
would), and jitted once. A configuration that diverges keeps its last good state and stops
there while the others go on.

With `devices` other than 1 the config axis is laid out over a device mesh
(`cdrl.training.parallel.ConfigAxis`): the configurations are padded to a multiple of the device
count with copies of the last one (trained, never reported), each device runs the same vmapped
step on its block under `jax.shard_map`, still one program jitted once, and each process feeds
and reads only the block it holds.
"""
from __future__ import annotations

import dataclasses
import functools
import itertools
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from cdrl.data.stream import Chunk, ChunkStream
from cdrl.models.base import Variant
from cdrl.runs.config import RunConfig
from cdrl.runs.sources import step_limit
from cdrl.training.loop import Job, LoopResult, Plan, Sink, enter_stage, host_loop, stage_schedule
from cdrl.training.lookahead import with_heads
from cdrl.training.monitor import group_names
from cdrl.training.optim import HParams
from cdrl.training.parallel import ConfigAxis, shard_configs
from cdrl.training.step import TrainState, init_opt_states, init_params, train_step_fn

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


@functools.lru_cache(maxsize=8)
def sharded_sweep_step(variant: Variant, mesh):
    """`sweep_step` with the config axis over `mesh`: every device steps its block."""
    return jax.jit(shard_configs(functools.partial(sweep_step_fn, variant), mesh), donate_argnums=0)


def init_sweep(variant: Variant, cfgs: Sequence[RunConfig]) -> tuple[TrainState, HParams]:
    """Stacked initial states and hyper-parameters, each configuration exactly as
    `cdrl train` would start it (parameters from `PRNGKey(seed)`)."""
    curricula = [c for c in cfgs if len(c.feed_curriculum) > 1]
    if curricula:
        raise ValueError(f"a sweep trains each configuration at one multi-step K; multistep "
                         f"{curricula[0].multistep!r} is a curriculum: train it with cdrl train")
    fed = any(c.feed_curriculum[0] > 1 for c in cfgs)  # one program for the grid
    hps = stack([c.hparams(variant, fed=fed) for c in cfgs])
    keys = jnp.stack([jax.random.PRNGKey(c.seed) for c in cfgs])
    params = init_params(variant, keys, hps.lookahead)
    carry = variant.init_carry(cfgs[0].batch)
    states = TrainState(
        params=params,
        opt_state=jax.vmap(init_opt_states)(hps, params),
        carry=jax.tree.map(lambda x: jnp.broadcast_to(x, (len(cfgs),) + x.shape), carry),
        step=jnp.zeros((len(cfgs),), jnp.int32),
    )
    return states, hps


def held_configs(cfgs: Sequence[RunConfig], axis: ConfigAxis) -> list[RunConfig]:
    """The configurations of this process's block, padding (a copy of the last) included."""
    return [cfgs[min(i, len(cfgs) - 1)] for i in axis.local]


def make_streams(cfgs: Sequence[RunConfig], train_eps_of: Callable[[RunConfig], Sequence]) -> dict:
    """One data stream per seed of `cfgs`."""
    streams = {}
    for c in cfgs:
        if c.seed not in streams:
            episodes = train_eps_of(c)
            streams[c.seed] = ChunkStream(episodes, c.batch, c.unroll, image_size=c.arch.image_size,
                                          action_dim=c.arch.action_dim, seed=c.seed, step_limit=step_limit(episodes))
    return streams


class SweepJob(Job):
    """The host loop's job of a grid: every configuration of this process's block a lane of
    one vmapped step (`sweep_step`, or its sharded form over `axis`), each with its seed's
    data stream. A configuration that diverges stops while the others go on. Hooks for a
    sweep's run directories (`cdrl.runs.sweep`) are `evaluate_lanes` and `save_lanes`."""

    stop_on_divergence = False

    def __init__(self, variant: Variant, cfgs: Sequence[RunConfig], streams: dict[int, ChunkStream], steps: int,
                 axis: ConfigAxis | None = None):
        self.variant, self.cfgs, self.streams = variant, cfgs, streams
        self.axis = axis or ConfigAxis(None, len(cfgs))
        self.held = held_configs(cfgs, self.axis)
        self.real = [i < len(cfgs) for i in self.axis.local]
        self.lanes = len(self.held)
        self.desc = f"sweep {variant.name} x{len(cfgs)}"
        self.frames_per_step = cfgs[0].batch * cfgs[0].unroll
        heads = cfgs[0].lookahead_hparams()
        self.ratio_names = group_names(jax.eval_shape(lambda k: with_heads(variant, variant.init(k), k, heads),
                                                      jax.random.PRNGKey(0)))
        self.threshold = float(cfgs[0].diverge_threshold)
        self.schedule = stage_schedule(variant, steps)
        self.switches = {first for first, _ in self.schedule}
        self.step_fn = (functools.partial(sweep_step, variant) if self.axis.mesh is None
                        else sharded_sweep_step(variant, self.axis.mesh))

    def init(self, resumed: tuple[TrainState, np.ndarray] | None = None) -> tuple[TrainState, list[bool]]:
        """This block's stacked initial states (or `resumed`'s) and which lanes train."""
        states, self.hps = init_sweep(self.variant, self.held)
        alive = np.asarray(self.real)
        if resumed is not None:
            states, alive = resumed[0], np.asarray(resumed[1], bool) & alive
        self.alive = self.axis.to_global(jnp.asarray(alive))
        return states, alive.tolist()

    def stage(self, step, states, resumed):
        if resumed:  # the stage the run (re)starts in; the block goes onto the devices
            states, self.hps = enter_stage(self.variant, self.schedule, step, states, self.hps, resumed=step > 0)
            self.placed_hps = self.axis.to_global(self.hps)
            return self.axis.to_global(states)
        if step in self.switches:  # a new stage: its loss weights, fresh momentum
            local, self.hps = enter_stage(self.variant, self.schedule, step, self.axis.to_local(states), self.hps)
            self.placed_hps = self.axis.to_global(self.hps)
            return self.axis.to_global(local)
        return states

    def step(self, states):
        chunk_of = {seed: stream.next_chunk() for seed, stream in self.streams.items()}
        chunks = self.axis.to_global(jax.tree.map(lambda *xs: np.stack(xs), *[chunk_of[c.seed] for c in self.held]))
        states, self.alive, metrics = self.step_fn(states, self.placed_hps, self.alive, chunks)
        return states, self.axis.to_local(metrics)

    def local_states(self, states) -> TrainState:
        """This block's stacked states out of the global ones."""
        return self.axis.to_local(states)


def run_grid(variant: Variant, cfgs: Sequence[RunConfig], streams: dict[int, ChunkStream], steps: int,
             axis: ConfigAxis | None = None) -> LoopResult:
    """`steps` train steps of every configuration of `cfgs` through the host loop, recording
    nothing: this process's block (`axis.local`), each seed's data from `streams`. The
    result's state is the block's stacked final states."""
    job = SweepJob(variant, cfgs, streams, steps, axis)
    states, alive = job.init()
    result = host_loop(job, states, Plan(steps=steps, final_eval=False), [Sink() for _ in range(job.lanes)], alive)
    return dataclasses.replace(result, state=job.local_states(result.state))
