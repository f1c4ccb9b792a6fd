"""The thesis's divergence check as an optax transformation.

For every parameter group (each kernel, each bias: one leaf of the parameter pytree) the
monitor records ||grad|| / ||param||. Ratios much larger than one mean the run diverges;
the thesis picked its learning rate by lowering it until no ratio did (section 4.3.1).

Unlike `optax.contrib`-style monitors that grow their state, the state here has the fixed
structure of the parameters (one scalar per leaf), so the transformation is safe inside
`jax.lax.scan` and `jax.vmap`. Place it first in a chain so it sees the raw gradients.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax


class NormRatioState(NamedTuple):
    """`ratios` has the parameters' tree structure with one scalar ratio per leaf."""

    ratios: optax.Params


def leaf_ratio(grad: jax.Array, param: jax.Array) -> jax.Array:
    """||grad|| / ||param||; a group whose parameters are all zero (a fresh bias) reports 0."""
    p_norm = jnp.sqrt(jnp.sum(jnp.square(param)))
    g_norm = jnp.sqrt(jnp.sum(jnp.square(grad)))
    return jnp.where(p_norm > 0, g_norm / jnp.where(p_norm > 0, p_norm, 1.0), 0.0)


def norm_ratio_monitor() -> optax.GradientTransformation:
    """Records per-group gradient-norm / parameter-norm ratios; passes updates unchanged."""

    def init_fn(params):
        return NormRatioState(jax.tree.map(lambda p: jnp.zeros((), jnp.float32), params))

    def update_fn(updates, state, params=None):
        del state
        if params is None:
            raise ValueError("norm_ratio_monitor needs the parameters: call update(grads, state, params)")
        return updates, NormRatioState(jax.tree.map(leaf_ratio, updates, params))

    return optax.GradientTransformation(init_fn, update_fn)


def group_names(tree) -> list[str]:
    """'/'-joined key paths of the leaves, in `jax.tree.leaves` order (e.g. 'obs_enc/conv3/kernel')."""
    paths = jax.tree_util.tree_flatten_with_path(tree)[0]
    return ["/".join(_key_str(k) for k in path) for path, _ in paths]


def _key_str(key) -> str:
    for attr in ("key", "name", "idx"):
        if hasattr(key, attr):
            return str(getattr(key, attr))
    return str(key)
