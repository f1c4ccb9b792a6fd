"""Cheap counter-based random numbers for the game's inner loop.

``jax.random`` (threefry) is lowered on CPU to a rolled loop whose overhead
dominated a game step, so the game, the policies and the collectors draw their
numbers by hashing the key's bits with a counter instead: a few integer
multiply/xor-shift rounds (the "lowbias32" mixer), fully vectorised and
loop-free.  Uniform draws are materialised (:func:`envs._xla.materialise`) so
that XLA computes the hash once instead of repeating it inside every element of its
consumers.  Keys are ordinary JAX PRNG keys (``jax.random.PRNGKey`` arrays or typed
``jax.random.key``); :func:`split` and :func:`fold_in` return ``PRNGKey``-style
``uint32[2]`` arrays, which ``jax.random`` also accepts.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from envs._xla import materialise

_GOLDEN = np.uint32(0x9E3779B9)
_M1 = np.uint32(0x7FEB352D)
_M2 = np.uint32(0x846CA68B)


def _mix(x: jnp.ndarray) -> jnp.ndarray:
    """The lowbias32 integer hash (a bijection on uint32)."""
    x = x ^ (x >> 16)
    x = x * _M1
    x = x ^ (x >> 15)
    x = x * _M2
    return x ^ (x >> 16)


def _words(key) -> tuple[jnp.ndarray, jnp.ndarray]:
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    key = jnp.asarray(key, jnp.uint32)
    return key[..., 0], key[..., -1]


def bits(key, n: int) -> jnp.ndarray:
    """``n`` pseudo-random uint32 values from ``key`` (a single key)."""
    k0, k1 = _words(key)
    counter = jnp.arange(n, dtype=jnp.uint32)
    return _mix(_mix(_mix(counter * _GOLDEN + k1) ^ k0) + counter)


def uniform(key, n: int) -> jnp.ndarray:
    """``n`` float32 values uniform in [0, 1) from ``key``."""
    (u,) = materialise((bits(key, n) >> 8).astype(jnp.float32) * np.float32(1.0 / (1 << 24)))
    return u


def split(key, n: int = 2) -> jnp.ndarray:
    """``n`` new keys ``uint32[n, 2]`` derived from ``key``."""
    b = bits(key, 2 * n)
    return b.reshape(n, 2) ^ jnp.asarray([0x5BD1E995, 0x27D4EB2F], jnp.uint32)


def fold_in(key, data) -> jnp.ndarray:
    """A new key ``uint32[2]`` from ``key`` and an integer ``data``."""
    k0, k1 = _words(key)
    d = jnp.asarray(data).astype(jnp.uint32)
    a = _mix(k0 ^ _mix(d * _GOLDEN + np.uint32(0x632BE5AB)))
    b = _mix(k1 + _mix(d ^ np.uint32(0x85157AF5)))
    return jnp.stack([a, b ^ a], axis=-1)
