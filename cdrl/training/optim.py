"""The optimiser and the traced hyper-parameters of offline training."""
from __future__ import annotations

import flax.struct
import jax
import jax.numpy as jnp
import optax

from cdrl.models.base import Variant
from cdrl.training.monitor import norm_ratio_monitor


@flax.struct.dataclass
class HParams:
    """Traced hyper-parameters: one compiled program serves any values (and a `vmap` sweep)."""

    lr: jax.Array
    momentum: jax.Array
    loss_weights: dict[str, jax.Array]
    diverge_threshold: jax.Array

    @classmethod
    def create(
        cls,
        variant: Variant,
        lr: float = 0.1,
        momentum: float = 0.9,
        loss_weights: dict[str, float] | None = None,
        diverge_threshold: float = 1e3,
    ) -> "HParams":
        weights = dict(variant.default_loss_weights())
        for key, value in (loss_weights or {}).items():
            if key not in weights:
                raise ValueError(
                    f"unknown loss term {key!r} for variant {variant.name!r}; "
                    f"its terms are {sorted(weights)}"
                )
            weights[key] = value
        f32 = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
        return cls(f32(lr), f32(momentum), {k: f32(v) for k, v in weights.items()}, f32(diverge_threshold))


def make_optimizer(hp: HParams) -> optax.GradientTransformation:
    """Monitor first (raw gradients), then SGD: mu <- beta mu + g; w <- w - lr mu."""
    return optax.chain(norm_ratio_monitor(), optax.sgd(hp.lr, momentum=hp.momentum))


