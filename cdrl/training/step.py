"""Truncated back-propagation through time: one pure, jitted train step.

`train_step(variant, state, hparams, chunk) -> (state, metrics)` unrolls the variant over
one T-step chunk of B streams, averages the weighted loss terms, applies SGD with momentum,
and reports the per-group norm ratios of the divergence monitor. The carry at the end of
the chunk becomes the next chunk's initial carry, behind a stop-gradient (the TBPTT cut);
episode starts inside a chunk reset the carry of their stream only.

A step whose loss, gradients or parameters are not finite, or whose largest norm ratio of
a kernel (`watched_groups`) exceeds `hparams.diverge_threshold`, is marked `diverged` and leaves the state unchanged,
so the host keeps the last good parameters.
"""
from __future__ import annotations

import functools
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import optax

from cdrl.data.frames import as_float
from cdrl.data.stream import Chunk
from cdrl.models.base import StepInput, Variant
from cdrl.training import lookahead
from cdrl.training.monitor import NormRatioState, group_names
from cdrl.training.optim import HParams, OptHParams, init_opt_state, make_optimizer


@flax.struct.dataclass
class TrainState:
    params: Any
    opt_state: Any
    carry: Any  # the recurrent state of every stream, carried across chunks
    step: jax.Array


# Programs that run once (initialisers) compile without LLVM optimisation: the many
# truncated-normal samplers of an init take XLA ~16 s to optimise for the tiny preset on two
# cores and ~1.4 s not to, for a program that then runs once.
RUN_ONCE = {"xla_backend_optimization_level": 0}


def run_once(fn, *args, static_argnums: tuple[int, ...] = ()):
    """`jax.jit(fn, static_argnums)(*args)`, compiled for a single call (see `RUN_ONCE`).
    Under a transformation (`jax.eval_shape`, an outer `jit`) it is `fn(*args)`."""
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(args)):
        return fn(*args)
    compiled = jax.jit(fn, static_argnums=static_argnums).lower(*args).compile(compiler_options=RUN_ONCE)
    return compiled(*[a for i, a in enumerate(args) if i not in static_argnums])


def init_params(variant: Variant, key: jax.Array, heads: lookahead.LookaheadHParams | None = None):
    """The variant's initial parameters from `key` (or stacked, from a stack of keys), with the
    look-ahead heads where `heads` is given."""
    init = functools.partial(_init_with_heads, variant, heads)
    return run_once(jax.vmap(init) if key.ndim > 1 else init, key)


def _init_with_heads(variant: Variant, heads, key):
    return lookahead.with_heads(variant, variant.init(key), key, heads)


def init_opt_states(hp: HParams, params):
    """The optimiser state of `params`: the model's, and with look-ahead heads the pair of the
    model's and the heads' own (`LookaheadHParams.head_opt`)."""
    if hp.lookahead is None:
        return init_opt_state(hp.opt, params)
    return init_opt_state(hp.opt, params), init_opt_state(hp.lookahead.head_opt, params["lookahead"])


def init_state(variant: Variant, key: jax.Array, batch: int, hp: HParams | None = None) -> TrainState:
    hp = hp if hp is not None else HParams.create(variant)
    params = init_params(variant, key, hp.lookahead)
    return TrainState(
        params=params,
        opt_state=init_opt_states(hp, params),
        carry=variant.init_carry(batch),
        step=jnp.zeros((), jnp.int32),
    )


def step_inputs(chunk: Chunk) -> StepInput:
    return StepInput(obs=as_float(chunk.obs), action=chunk.action.astype(jnp.float32), is_first=chunk.is_first)


def mirrored_streams(chunk: Chunk) -> Chunk:
    """The chunk with its second half of streams (b >= B - B // 2) seen in a mirror: frames
    reversed left to right, the turn buttons swapped (`envs.symmetry.MIRRORED_BUTTONS`). The
    game is symmetric, so a mirrored episode is one it could play. A stream keeps its side for
    every chunk, so the carry it hands on saw the same side."""
    from envs.symmetry import MIRRORED_BUTTONS

    b = chunk.obs.shape[1]
    flip = jnp.arange(b) >= b - b // 2
    frames = lambda x: jnp.where(flip[None, :, None, None], x[..., ::-1], x)  # noqa: E731
    action = jnp.where(flip[None, :, None], chunk.action[..., jnp.asarray(MIRRORED_BUTTONS)], chunk.action)
    return chunk.replace(obs=frames(chunk.obs), next_obs=frames(chunk.next_obs), action=action)


def chunk_loss(variant: Variant, params, carry, hp: HParams, chunk: Chunk):
    """Weighted loss of one chunk from `carry`, which is cut from the graph (TBPTT); with
    `hp.fed`, the model is fed its own predictions between real frames (`HParams.feed_every`);
    with `hp.mirror`, half of the streams see the game in a mirror (`mirrored_streams`).

    Returns `(loss, (final_carry, terms, outputs))`.
    """
    if hp.mirror:
        chunk = mirrored_streams(chunk)
    carry = jax.lax.stop_gradient(carry)
    xs = step_inputs(chunk)
    next_obs = as_float(chunk.next_obs)
    if hp.fed:  # multi-step training: real frames every `feed_every` steps, own predictions between
        t = jnp.arange(xs.is_first.shape[0])[:, None]
        carry, outs = variant.unroll_fed(params, carry, xs, (t % hp.feed_every == 0) | xs.is_first)
    elif hp.lookahead is not None:  # every step's carry, where the imagined steps start
        carry, outs, carries = variant.unroll_states(params, carry, xs)
    else:
        carry, outs = variant.unroll(params, carry, xs)
    terms = variant.loss_terms(params, xs, outs, next_obs, chunk.reward)
    if hp.lookahead is not None:
        terms.update(lookahead.lookahead_terms(variant, params, hp.lookahead, xs, outs, carries, next_obs,
                                               chunk.reward, chunk.truncated))
    missing = set(terms) ^ set(hp.loss_weights)
    if missing:
        raise ValueError(f"loss weights and terms differ for {variant.name!r}: {sorted(missing)}")
    loss = sum(hp.loss_weights[k] * terms[k] for k in sorted(terms))
    return loss, (carry, terms, outs)


def all_finite(tree) -> jax.Array:
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(tree)]))


def watched_groups(params) -> jax.Array:
    """Which groups the divergence check watches: the kernels and weight matrices (the
    groups the thesis plots). Biases start at zero, so right after the first update their
    ratio is about 1 / lr whatever the run does; their ratios are logged, not watched."""
    return jnp.array([leaf.ndim >= 2 for leaf in jax.tree.leaves(params)])


def guarded_update(opt: OptHParams, threshold: jax.Array, params, opt_state, grads, loss: jax.Array):
    """One optimiser update behind the divergence guard. The update is refused when the loss,
    a gradient or an updated parameter is not finite, or when a watched group's norm ratio
    ||grad|| / ||param|| exceeds `threshold`: then the old parameters and optimiser state come
    back. Returns `(params, opt_state, metrics)` with the monitor's `ratios` (every group, in
    `group_names` order), `max_ratio` and `worst_group` (over the watched groups), `finite`
    and `diverged`."""
    updates, new_opt_state = make_optimizer(opt).update(grads, opt_state, params)
    new_params = optax.apply_updates(params, updates)
    monitor: NormRatioState = new_opt_state[0]
    ratios = jnp.stack(jax.tree.leaves(monitor.ratios))
    safe = jnp.where(jnp.isfinite(ratios), ratios, jnp.inf)
    safe = jnp.where(watched_groups(params), safe, 0.0)
    finite = jnp.isfinite(loss) & all_finite(grads) & all_finite(new_params)
    max_ratio = jnp.max(safe)
    diverged = ~finite | (max_ratio > threshold)
    keep = lambda new, old: jax.tree.map(lambda n, o: jnp.where(diverged, o, n), new, old)  # noqa: E731
    metrics = {"ratios": ratios, "max_ratio": max_ratio, "worst_group": jnp.argmax(safe), "finite": finite,
               "diverged": diverged}
    return keep(new_params, params), keep(new_opt_state, opt_state), metrics


def heads_apart_update(hp: HParams, params, opt_state, grads, loss: jax.Array):
    """`guarded_update` of a model with look-ahead heads: the model's optimiser moves the
    model, the heads' own (`LookaheadHParams.head_opt`) moves the heads, then the value's target
    copy follows its head (`lookahead.update_target`). Either refusing refuses both.
    `opt_state` is the pair of `init_opt_states`."""
    model_state, heads_state = opt_state
    model_grads = {**grads, "lookahead": jax.tree.map(jnp.zeros_like, grads["lookahead"])}
    new, new_model_state, guard = guarded_update(hp.opt, hp.diverge_threshold, params, model_state, model_grads,
                                                 loss)
    heads, new_heads_state, heads_guard = guarded_update(hp.lookahead.head_opt, hp.diverge_threshold,
                                                         params["lookahead"], heads_state, grads["lookahead"], loss)
    new = lookahead.update_target({**new, "lookahead": heads}, hp.lookahead)
    diverged = guard["diverged"] | heads_guard["diverged"]
    keep = lambda n, o: jax.tree.map(lambda a, b: jnp.where(diverged, b, a), n, o)  # noqa: E731
    guard = {**guard, "finite": guard["finite"] & heads_guard["finite"], "diverged": diverged}
    return keep(new, params), keep((new_model_state, new_heads_state), opt_state), guard


def train_step_fn(variant: Variant, state: TrainState, hp: HParams, chunk: Chunk):
    """The un-jitted train step (for `vmap`/`scan` compositions); see `train_step`."""
    grad_fn = jax.value_and_grad(functools.partial(chunk_loss, variant), has_aux=True)
    (loss, (carry, terms, _)), grads = grad_fn(state.params, state.carry, hp, chunk)
    if hp.lookahead is None:
        params, opt_state, guard = guarded_update(hp.opt, hp.diverge_threshold, state.params, state.opt_state, grads,
                                                  loss)
    else:
        params, opt_state, guard = heads_apart_update(hp, state.params, state.opt_state, grads, loss)
    # A refused step leaves the whole state as it was, the streams' carries included.
    carry = jax.tree.map(lambda n, o: jnp.where(guard["diverged"], o, n), carry, state.carry)
    step = state.step + jnp.where(guard["diverged"], 0, 1)
    state = TrainState(params=params, opt_state=opt_state, carry=carry, step=step)
    return state, {"loss": loss, "terms": terms, **guard}


train_step = jax.jit(train_step_fn, static_argnums=0, donate_argnums=1)


def ratio_names(state: TrainState) -> list[str]:
    """Names of the entries of `metrics['ratios']`, in order."""
    return group_names(state.params)
