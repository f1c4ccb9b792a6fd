"""Two-hot codes over symlog-spaced bins (DreamerV3): how the look-ahead heads predict reward
and value as a distribution and read back their expected value."""
from __future__ import annotations

import jax
import jax.numpy as jnp


def symlog(x: jax.Array) -> jax.Array:
    return jnp.sign(x) * jnp.log1p(jnp.abs(x))


def symexp(x: jax.Array) -> jax.Array:
    return jnp.sign(x) * jnp.expm1(jnp.abs(x))


def two_hot(y: jax.Array, bins: jax.Array) -> jax.Array:
    """`[..., N]`: y (clipped to the bins) split between its two nearest `bins`, each weighted by
    its nearness, so that the weights sum to 1 and their mean over the bins is y."""
    y = jnp.clip(y, bins[0], bins[-1])
    low = jnp.clip(jnp.searchsorted(bins, y, side="right") - 1, 0, bins.shape[0] - 2)
    upper = (y - bins[low]) / (bins[low + 1] - bins[low])
    n = bins.shape[0]
    return jax.nn.one_hot(low, n) * (1.0 - upper)[..., None] + jax.nn.one_hot(low + 1, n) * upper[..., None]


def two_hot_loss(logits: jax.Array, target: jax.Array, bins: jax.Array) -> jax.Array:
    """Cross-entropy of softmax(`logits`) against the two-hot code of symlog(`target`)."""
    return -jnp.sum(two_hot(symlog(target), bins) * jax.nn.log_softmax(logits), axis=-1)


def expected(logits: jax.Array, bins: jax.Array) -> jax.Array:
    """The value a two-hot head predicts: symexp of the bins' mean under softmax(`logits`)."""
    return symexp(jnp.sum(jax.nn.softmax(logits) * bins, axis=-1))
