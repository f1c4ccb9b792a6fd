"""Held-out evaluation: mean next-frame BCE, the copy-last-frame baseline on the same frames,
the targets' own entropy (the floor no prediction can beat on grey-level frames), and (for
variants that share their code space) the code-prediction error MSE(d_{t+1}, k_{t+1}).

Each episode is run from a zero carry in chunks of T steps (the last chunk padded and
masked), so evaluation uses one compiled program whatever the episode lengths.
"""
from __future__ import annotations

import functools
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from cdrl.data.episode import Episode
from cdrl.data.frames import as_float
from cdrl.data.stream import Chunk
from cdrl.models.base import Variant
from cdrl.training.step import step_inputs

# The copy-last-frame baseline predicts clip(o_t, COPY_EPS, 1 - COPY_EPS): a hard 0/1 copy
# would have an infinite BCE wherever a pixel flips.
COPY_EPS = 0.01


def _pixel_bce(logits, target):
    return jnp.mean(jax.nn.softplus(logits) - target * logits, axis=(-2, -1))


@functools.partial(jax.jit, static_argnums=0)
def eval_chunk_stats(variant: Variant, params, carry, chunk: Chunk):
    """Per-step statistics `[T, B]` of one chunk: model BCE, copy BCE, code error."""
    xs = step_inputs(chunk)
    carry, outs = variant.unroll(params, carry, xs)
    target = as_float(chunk.next_obs)
    copy = jnp.clip(xs.obs, COPY_EPS, 1 - COPY_EPS)
    p = jnp.clip(target, 1e-7, 1 - 1e-7)
    stats = {
        "bce": _pixel_bce(outs["logits"], target),
        # The floor of any prediction's BCE: the targets' own entropy (BCE - entropy = KL >= 0).
        "target_entropy": jnp.mean(-(p * jnp.log(p) + (1 - p) * jnp.log1p(-p)), axis=(-2, -1)),
        "copy_bce": _pixel_bce(jnp.log(copy) - jnp.log1p(-copy), target),
    }
    if variant.shared_code_space:
        pred = outs["pred_code"][:-1]
        code = outs["code"][1:, ..., : pred.shape[-1]]
        err = jnp.mean(jnp.square(pred - code), axis=-1)
        stats["code_pred_mse"] = jnp.concatenate([err, jnp.full_like(err[:1], jnp.nan)], axis=0)
    return carry, stats


def evaluate(variant: Variant, params, episodes: Sequence[Episode], unroll: int = 32) -> dict[str, float]:
    """Mean per-frame statistics over every transition of `episodes`."""
    if len(episodes) == 0:
        raise ValueError("no episodes to evaluate on")
    sums: dict[str, float] = {}
    counts: dict[str, int] = {}
    for ep in episodes:
        n = len(ep) - 1
        carry = variant.init_carry(1)
        for start in range(0, n, unroll):
            idx = np.minimum(np.arange(start, start + unroll), n - 1)
            valid = np.arange(start, start + unroll) < n
            chunk = Chunk(
                obs=ep.frames[idx][:, None],
                next_obs=ep.frames[idx + 1][:, None],
                action=ep.actions[idx][:, None].astype(np.float32),
                reward=ep.rewards[idx + 1][:, None].astype(np.float32),
                is_first=((idx == 0) & (np.arange(unroll) == 0))[:, None],
            )
            carry, stats = eval_chunk_stats(variant, params, carry, chunk)
            # A code-prediction pair needs its next step inside the episode too.
            pair_valid = valid & np.append(valid[1:], False)
            for key, value in jax.device_get(stats).items():
                value = np.asarray(value)[:, 0][pair_valid if key == "code_pred_mse" else valid]
                value = value[np.isfinite(value)]
                sums[key] = sums.get(key, 0.0) + float(value.sum())
                counts[key] = counts.get(key, 0) + value.size
    return {key: sums[key] / max(counts[key], 1) for key in sums}
