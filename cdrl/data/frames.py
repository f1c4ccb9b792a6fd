"""Frame conversions shared by training, evaluation and play."""
from __future__ import annotations

import jax
import jax.numpy as jnp


def as_float(frames: jax.Array) -> jax.Array:
    """uint8 frames to [0, 1]; float frames unchanged."""
    if frames.dtype == jnp.uint8:
        return frames.astype(jnp.float32) / 255.0
    return frames.astype(jnp.float32)


def resize_obs(obs: jax.Array, size: int) -> jax.Array:
    """Game observations `[..., S, S]` to the model's `size` (area-averaging when shrinking)."""
    if obs.shape[-1] == size:
        return obs
    shape = obs.shape[:-2] + (size, size)
    return jax.image.resize(obs, shape, method="linear", antialias=True)
