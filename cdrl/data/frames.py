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


def max_filter(frames: jax.Array, k: int) -> jax.Array:
    """Each pixel of `frames` `[..., H, W]` replaced by the brightest of the k x k window around
    it (grey-level dilation; the window is cut at the frame's edges). k = 1 leaves them as they are."""
    if k < 1:
        raise ValueError(f"max filter side must be >= 1, got {k}")
    if k == 1:
        return frames
    lead = frames.ndim - 2
    return jax.lax.reduce_window(frames, -jnp.inf, jax.lax.max, (1,) * lead + (k, k), (1,) * frames.ndim,
                                 [(0, 0)] * lead + [(k // 2, k - 1 - k // 2)] * 2)


def resize_obs(obs: jax.Array, size: int, max_filter_size: int = 1) -> jax.Array:
    """Game observations `[..., S, S]` to the model's `size`: area-averaging when shrinking,
    after a `max_filter_size` max filter (`ArchConfig.max_filter`), which keeps a small bright
    object (a pellet) near its brightness where the average alone would spread it into the
    background. A frame already at `size` is returned as it is."""
    if obs.shape[-1] == size:
        return obs
    obs = max_filter(obs, max_filter_size)
    shape = obs.shape[:-2] + (size, size)
    return jax.image.resize(obs, shape, method="linear", antialias=True)


def model_obs(obs: jax.Array, arch) -> jax.Array:
    """The game's observations `[..., S, S]` as a model of architecture `arch` (an
    `ArchConfig`) sees them: `resize_obs` to its `image_size` after its `max_filter`."""
    return resize_obs(obs, arch.image_size, arch.max_filter)
