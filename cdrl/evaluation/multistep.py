"""Multi-step prediction: how a model's predictions hold when it is fed its own output.

From a real context of C frames (teacher-forced, from a zero carry) the model predicts the
next frame, then is fed the sigmoid of its own prediction for the K - 1 steps after, the
recorded actions still entering the action variants. Step k = 1 .. K is the prediction of
o_{C-1+k}: step 1 is the ordinary one-step prediction, steps 2 .. K are open loop. Each step is
scored as one-step prediction is, against copying the last real frame o_{C-1} for the same
horizon, above the floor (the target frame's entropy): the excess ratio at step k is
(BCE_k - floor_k) / (copy-last BCE_k - floor_k), below 1 where the model beats holding its
last real frame k steps ahead.

How each variant's data flow runs open loop: the observation variants take their own predicted
frame as o_t; the residual ones add their predicted code to it as they do to a real frame; closed
loop − takes o_t − õ_t, which is zero when o_t is its own prediction õ_t (the thesis's argument
for it, section 6: it then runs on its memory alone), closed loop + 2 õ_t.
"""
from __future__ import annotations

import functools
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from cdrl.data.episode import Episode
from cdrl.data.frames import as_float, copy_last_bce, pixel_bce, target_entropy
from cdrl.evaluation.metrics import excess_ratio
from cdrl.models.base import StepInput, Variant


@functools.partial(jax.jit, static_argnums=(0, 4))
def open_loop(variant: Variant, params, frames: jax.Array, actions: jax.Array, horizon: int) -> jax.Array:
    """Logits `[C + horizon - 1, B, H, W]` of the frames after each step: teacher-forced on the
    C context `frames` `[C, B, H, W]`, then each step fed with the sigmoid of the model's own
    previous prediction (`Variant.unroll_fed`); `actions` `[C + horizon - 1, B, A]` are the
    actions of those steps."""
    context, batch = frames.shape[:2]
    steps = context + horizon - 1
    obs = jnp.concatenate([frames, jnp.zeros((horizon - 1,) + frames.shape[1:], frames.dtype)])
    t = jnp.arange(steps)[:, None]
    xs = StepInput(obs=obs, action=actions[:steps], is_first=jnp.broadcast_to(t == 0, (steps, batch)))
    _, outs = variant.unroll_fed(params, variant.init_carry(batch), xs, jnp.broadcast_to(t < context, (steps, batch)))
    return outs["logits"]


@functools.partial(jax.jit, static_argnums=(0, 4))
def _window_scores(variant: Variant, params, frames: jax.Array, actions: jax.Array, context: int):
    """Per step k and window `[K, B]`: the BCE of the model's prediction, of copying the last
    real frame, and the floor, for windows `frames` `[C + K, B, H, W]`."""
    horizon = frames.shape[0] - context
    logits = open_loop(variant, params, frames[:context], actions[:-1], horizon)[context - 1:]
    targets = frames[context:]
    last = jnp.broadcast_to(frames[context - 1], targets.shape)
    return pixel_bce(logits, targets), copy_last_bce(last, targets), target_entropy(targets)


def windows(episodes: Sequence[Episode], length: int) -> list[tuple[int, int]]:
    """(episode, start) of every window of `length` frames, back to back within each episode."""
    return [(i, s) for i in range(len(episodes)) for s in range(0, len(episodes[i]) - length + 1, length)]


def multistep_scores(variant: Variant, params, episodes: Sequence[Episode], context: int = 8, horizon: int = 15,
                     batch: int = 16) -> dict:
    """The excess ratio of open-loop predictions at steps 1 .. `horizon` after `context` real
    frames, over every window of C + K frames of `episodes` (back to back; up to `batch`
    windows side by side). Returns `context`, `horizon`, `windows`, and per step lists `bce`,
    `copy_bce`, `target_entropy`, `excess_ratio`."""
    if context < 1 or horizon < 1:
        raise ValueError(f"context and horizon must be >= 1, got {context} and {horizon}")
    spans = windows(episodes, context + horizon)
    if not spans:
        longest = max((len(ep) for ep in episodes), default=0)
        raise ValueError(f"no episode holds context + horizon = {context + horizon} frames (the longest has "
                         f"{longest}); shorten --context or --horizon")
    sums = np.zeros((3, horizon))
    for first in range(0, len(spans), batch):
        group = spans[first: first + batch]
        group = group + [group[0]] * (batch - len(group)) if len(spans) > batch else group
        take = lambda field, convert: np.stack([  # noqa: E731
            convert(getattr(episodes[i], field)[s: s + context + horizon]) for i, s in group], axis=1)
        frames = take("frames", as_float)
        actions = take("actions", lambda a: np.asarray(a, np.float32))
        scores = jax.device_get(_window_scores(variant, params, frames, actions, context))
        real = min(batch, len(spans) - first)
        sums += np.stack([np.asarray(x, np.float64)[:, :real].sum(axis=1) for x in scores])
    bce, copy, floor = sums / len(spans)
    return {"context": context, "horizon": horizon, "windows": len(spans), "bce": bce.tolist(),
            "copy_bce": copy.tolist(), "target_entropy": floor.tolist(),
            "excess_ratio": [excess_ratio(*v) for v in zip(bce, copy, floor)]}
