"""Optimisers through optax, with traced hyper-parameters.

`OptHParams` holds the optimiser's numbers as arrays (learning rate, momentum / beta1,
beta2, weight decay, gradient clip, warm-up and cosine-decay lengths), so one compiled
program serves any values of them and a `vmap` over a stack of them trains a sweep. Only
the optimiser's name is static: it decides the structure of the optimiser state.

`make_optimizer(opt)` chains, in order: the norm-ratio monitor (it sees the raw gradients,
as the thesis's divergence check does), global-norm gradient clipping (off at 0), and the
optimiser with its learning-rate schedule. The thesis's rule is `sgd` with a constant rate:
mu <- beta mu + g; w <- w - lr mu.

`HParams` adds what offline training weighs and watches: the loss-term weights and the
divergence threshold.
"""
from __future__ import annotations

from typing import Any, Callable

import flax.struct
import jax
import jax.numpy as jnp
import optax

from cdrl.models.base import Variant
from cdrl.training.monitor import norm_ratio_monitor

Schedule = Callable[[jax.Array], jax.Array]


def _sgd(lr: Schedule, o: "OptHParams") -> optax.GradientTransformation:
    return optax.sgd(lr, momentum=o.momentum)


def _adam(lr: Schedule, o: "OptHParams") -> optax.GradientTransformation:
    return optax.adam(lr, b1=o.momentum, b2=o.b2)


def _adamw(lr: Schedule, o: "OptHParams") -> optax.GradientTransformation:
    return optax.adamw(lr, b1=o.momentum, b2=o.b2, weight_decay=o.weight_decay)


def _rmsprop(lr: Schedule, o: "OptHParams") -> optax.GradientTransformation:
    return optax.rmsprop(lr, decay=o.b2, momentum=o.momentum)


def _lion(lr: Schedule, o: "OptHParams") -> optax.GradientTransformation:
    return optax.lion(lr, b1=o.momentum, b2=o.b2, weight_decay=o.weight_decay)


# name -> (builder, what `momentum` and `b2` mean for it)
OPTIMIZERS: dict[str, Callable[[Schedule, "OptHParams"], optax.GradientTransformation]] = {
    "sgd": _sgd,  # momentum: the thesis's beta; b2, weight_decay unused
    "adam": _adam,  # momentum: beta1; b2: beta2
    "adamw": _adamw,  # as adam, plus decoupled weight decay
    "rmsprop": _rmsprop,  # b2: decay of the squared-gradient average; momentum: momentum
    "lion": _lion,  # momentum: beta1; b2: beta2; weight decay
}
SCHEDULES = ("constant", "cosine")


@flax.struct.dataclass
class OptHParams:
    """The optimiser's traced numbers; `name` (one of `OPTIMIZERS`) is static.

    lr: peak learning rate; momentum: SGD's beta / Adam's beta1; b2: beta2 (Adam, Lion) or
    the squared-gradient decay (RMSprop); weight_decay: decoupled decay (AdamW, Lion);
    grad_clip: largest global gradient norm (0: no clipping); warmup: steps of linear
    warm-up from 0 to lr (0: none); decay_steps: length of the cosine decay from lr to 0,
    counted from step 0 and held at 0 after it (0: constant rate).
    """

    lr: jax.Array
    momentum: jax.Array
    b2: jax.Array
    weight_decay: jax.Array
    grad_clip: jax.Array
    warmup: jax.Array
    decay_steps: jax.Array
    name: str = flax.struct.field(pytree_node=False, default="sgd")

    @classmethod
    def create(cls, name: str = "sgd", lr: float = 0.1, momentum: float = 0.9, b2: float = 0.999,
               weight_decay: float = 0.0, grad_clip: float = 0.0, warmup: int = 0,
               decay_steps: int = 0) -> "OptHParams":
        if name not in OPTIMIZERS:
            raise ValueError(f"unknown optimizer {name!r}; choose one of {sorted(OPTIMIZERS)}")
        f32 = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
        return cls(f32(lr), f32(momentum), f32(b2), f32(weight_decay), f32(grad_clip), f32(warmup),
                   f32(decay_steps), name=name)

    def learning_rate(self, count: jax.Array) -> jax.Array:
        """The rate of update `count` (0-based): warm-up ramp times cosine decay."""
        t = count.astype(jnp.float32)
        ramp = jnp.where(self.warmup > 0, jnp.minimum(1.0, (t + 1.0) / jnp.maximum(self.warmup, 1.0)), 1.0)
        frac = jnp.clip(t / jnp.maximum(self.decay_steps, 1.0), 0.0, 1.0)
        decay = jnp.where(self.decay_steps > 0, 0.5 * (1.0 + jnp.cos(jnp.pi * frac)), 1.0)
        return self.lr * ramp * decay


def make_optimizer(opt: OptHParams) -> optax.GradientTransformation:
    """Monitor (raw gradients), clip (if `grad_clip` > 0), then the optimiser with its schedule.
    The state's structure depends only on `opt.name`."""
    max_norm = jnp.where(opt.grad_clip > 0, opt.grad_clip, jnp.inf)
    return optax.chain(norm_ratio_monitor(), optax.clip_by_global_norm(max_norm),
                       OPTIMIZERS[opt.name](opt.learning_rate, opt))


def init_opt_state(opt: OptHParams, params):
    """The optimiser's initial state for `params`. It depends on `opt.name` only, so `opt`
    may be a sweep's stack of hyper-parameters (vmap this over stacked parameters)."""
    return make_optimizer(OptHParams.create(opt.name)).init(params)


@flax.struct.dataclass
class HParams:
    """Traced hyper-parameters of offline training: one compiled program serves any values
    (and a `vmap` sweep over a stack of them).

    `feed_every` K: multi-step training, where a chunk's step t sees the real frame where
    t % K == 0 (and at episode starts) and the model's own previous prediction elsewhere (K 1:
    teacher forcing). It is traced, so a curriculum changes it without compiling again; the
    static `fed` says whether the program unrolls with fed-back predictions at all (the
    one-step unroll of the open-loop variants encodes a whole chunk at once, which a fed-back
    one cannot).

    `lookahead` turns on the losses over a few imagined steps and the heads on the model's
    state (`cdrl.training.lookahead`); its terms join `loss_weights`."""

    opt: OptHParams
    loss_weights: dict[str, jax.Array]
    diverge_threshold: jax.Array
    feed_every: jax.Array
    lookahead: Any = None  # `cdrl.training.lookahead.LookaheadHParams`: its losses and heads (None: off)
    fed: bool = flax.struct.field(pytree_node=False, default=False)
    # The second half of a chunk's streams is seen in a mirror (`cdrl.training.step.mirrored_streams`).
    mirror: bool = flax.struct.field(pytree_node=False, default=False)

    @classmethod
    def create(
        cls,
        variant: Variant,
        lr: float = 0.1,
        momentum: float = 0.9,
        loss_weights: dict[str, float] | None = None,
        diverge_threshold: float = 1e3,
        opt: OptHParams | None = None,
        feed_every: int = 1,
        fed: bool | None = None,
        lookahead=None,
        mirror: bool = False,
    ) -> "HParams":
        """`opt`: the optimiser's numbers (default: SGD with `lr` and `momentum`, which it
        replaces). `fed` defaults to `feed_every > 1`; a curriculum that starts at K 1 sets it.
        `lookahead`: a `LookaheadHParams` (its terms' weights default to its `default_weights`).
        `mirror`: the second half of every chunk's streams is seen mirrored."""
        weights = dict(variant.default_loss_weights())
        if lookahead is not None:
            if feed_every > 1 or fed:
                raise ValueError("multi-step feeding (feed_every > 1) and the look-ahead losses are two ways to train "
                                 "on the model's own predictions; choose one")
            weights.update(lookahead.default_weights())
        for key, value in (loss_weights or {}).items():
            if key not in weights:
                raise ValueError(
                    f"unknown loss term {key!r} for variant {variant.name!r}; "
                    f"its terms are {sorted(weights)}"
                )
            weights[key] = value
        f32 = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
        opt = opt if opt is not None else OptHParams.create(lr=lr, momentum=momentum)
        if feed_every < 1:
            raise ValueError(f"feed_every must be >= 1 (1: teacher forcing), got {feed_every}")
        return cls(opt, {k: f32(v) for k, v in weights.items()}, f32(diverge_threshold),
                   jnp.asarray(feed_every, jnp.int32), lookahead, fed=feed_every > 1 if fed is None else fed,
                   mirror=mirror)

    @property
    def lr(self) -> jax.Array:
        return self.opt.lr
