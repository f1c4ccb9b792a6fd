"""Frame conversions shared by training, evaluation and play, and the two per-pixel scores
of next-frame prediction that need no model: the copy-last-frame baseline and the floor."""
from __future__ import annotations

import jax
import jax.numpy as jnp

from cdrl.models.base import elementwise_bce


def as_float(frames: jax.Array) -> jax.Array:
    """uint8 frames to [0, 1]; float frames unchanged."""
    if frames.dtype == jnp.uint8:
        return frames.astype(jnp.float32) / 255.0
    return frames.astype(jnp.float32)


# The copy-last-frame baseline predicts clip(o_t, COPY_EPS, 1 - COPY_EPS): a hard 0/1 copy
# would have an infinite BCE wherever a pixel flips.
COPY_EPS = 0.01


def pixel_bce(logits: jax.Array, target: jax.Array) -> jax.Array:
    """Per-frame mean BCE of sigmoid(logits) against `target` in [0, 1] (over the last two axes)."""
    return jnp.mean(elementwise_bce(logits, target), axis=(-2, -1))


def copy_last_bce(obs: jax.Array, target: jax.Array) -> jax.Array:
    """Per-frame BCE of predicting o_{t+1} = o_t (clipped to [COPY_EPS, 1 - COPY_EPS])."""
    copy = jnp.clip(obs, COPY_EPS, 1 - COPY_EPS)
    return pixel_bce(jnp.log(copy) - jnp.log1p(-copy), target)


def target_entropy(target: jax.Array) -> jax.Array:
    """Per-frame entropy of the targets' pixels: the floor of any prediction's BCE on grey-level
    frames (BCE - entropy = KL >= 0)."""
    p = jnp.clip(target, 1e-7, 1 - 1e-7)
    return jnp.mean(-(p * jnp.log(p) + (1 - p) * jnp.log1p(-p)), axis=(-2, -1))


def resize_obs(obs: jax.Array, size: int) -> jax.Array:
    """Game observations `[..., S, S]` to the model's `size` (area-averaging when shrinking)."""
    if obs.shape[-1] == size:
        return obs
    shape = obs.shape[:-2] + (size, size)
    return jax.image.resize(obs, shape, method="linear", antialias=True)
