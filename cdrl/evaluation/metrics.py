"""Held-out evaluation: mean next-frame BCE, the copy-last-frame baseline on the same frames,
the targets' own entropy (the floor no prediction can beat on grey-level frames), the excess
ratio (BCE - floor) / (copy-last BCE - floor), and (for variants that share their code
space) the code-prediction error MSE(d_{t+1}, k_{t+1}).

Episodes run side by side from a zero carry in chunks of T steps (padded and masked), so
evaluation uses one compiled program whatever the episode lengths.
"""
from __future__ import annotations

import functools
import math
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from cdrl.data.episode import Episode
from cdrl.data.frames import as_float, copy_last_bce, pixel_bce, target_entropy
from cdrl.data.stream import Chunk
from cdrl.models.base import Variant, code_prediction_errors
from cdrl.training.step import step_inputs


def check_episodes(episodes: int | None) -> None:
    """Refuse an evaluation's number of episodes (or games; None: the run's own) below 1,
    before any work."""
    if episodes is not None and (isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1):
        raise ValueError(f"episodes must be >= 1, got {episodes!r}")


@functools.partial(jax.jit, static_argnums=0)
def eval_chunk_stats(variant: Variant, params, carry, chunk: Chunk):
    """Per-step statistics `[T, B]` of one chunk: model BCE, copy BCE, code error."""
    xs = step_inputs(chunk)
    carry, outs = variant.unroll(params, carry, xs)
    target = as_float(chunk.next_obs)
    stats = {
        "bce": pixel_bce(outs["logits"], target),
        "target_entropy": target_entropy(target),
        "copy_bce": copy_last_bce(xs.obs, target),
    }
    if variant.shared_code_space:
        err = code_prediction_errors(outs)
        stats["code_pred_mse"] = jnp.concatenate([err, jnp.full_like(err[:1], jnp.nan)], axis=0)
    return carry, stats


def excess_ratio(bce: float, copy_bce: float, floor: float) -> float:
    """(BCE - floor) / (copy-last BCE - floor) on the same frames: the figure of merit of a
    next-frame predictor. Below 1 the model beats copying the last frame; 0 is the floor.
    NaN where copying the last frame is already at the floor."""
    gap = copy_bce - floor
    return (bce - floor) / gap if gap > 0 else float("nan")


SCORES = ("bce", "copy_bce", "target_entropy", "excess_ratio", "code_pred_mse")


def prefixed(scores: dict[str, float], split: str) -> dict[str, float | None]:
    """`scores` as table cells: `{split}_{name}` for each of `SCORES`, None where missing or
    not finite."""
    cells = {}
    for key in SCORES:
        value = scores.get(key)
        cells[f"{split}_{key}"] = float(value) if value is not None and math.isfinite(value) else None
    return cells


def evaluate(variant: Variant, params, episodes: Sequence[Episode], unroll: int = 32,
             batch: int = 16) -> dict[str, float]:
    """Mean per-frame statistics over every transition of `episodes`, and the excess ratio.

    Up to `batch` episodes run side by side as the B streams of one chunk, each from a zero
    carry; shorter episodes are padded with their last frame and the padding is masked out.
    """
    if len(episodes) == 0:
        raise ValueError("no episodes to evaluate on")
    sums: dict[str, float] = {}
    counts: dict[str, int] = {}
    width = min(batch, len(episodes))
    for first in range(0, len(episodes), width):
        group = list(episodes[first: first + width])
        n = np.array([len(ep) - 1 for ep in group])
        n = np.concatenate([n, np.zeros(width - len(group), np.int64)])  # unused columns: nothing valid
        group += [group[0]] * (width - len(group))
        carry = variant.init_carry(width)
        for start in range(0, int(n.max()), unroll):
            steps = np.arange(start, start + unroll)[:, None]
            idx = np.minimum(steps, np.maximum(n, 1)[None, :] - 1)  # [T, B]
            valid = steps < n[None, :]
            cols = np.arange(width)[None, :]

            def take(field, offset):
                return np.stack([getattr(ep, field)[idx[:, b] + offset] for b, ep in enumerate(group)], axis=1)

            chunk = Chunk(
                obs=take("frames", 0),
                next_obs=take("frames", 1),
                action=take("actions", 0).astype(np.float32),
                reward=take("rewards", 1).astype(np.float32),
                is_first=(steps == 0) & (cols >= 0),
            )
            carry, stats = eval_chunk_stats(variant, params, carry, chunk)
            # A code-prediction pair needs its next step inside the episode too.
            pair_valid = valid & np.concatenate([valid[1:], np.zeros_like(valid[:1])], axis=0)
            for key, value in jax.device_get(stats).items():
                value = np.asarray(value)[pair_valid if key == "code_pred_mse" else valid]
                value = value[np.isfinite(value)]
                sums[key] = sums.get(key, 0.0) + float(value.sum())
                counts[key] = counts.get(key, 0) + value.size
    result = {key: sums[key] / max(counts[key], 1) for key in sums}
    result["excess_ratio"] = excess_ratio(result["bce"], result["copy_bce"], result["target_entropy"])
    return result
