"""Synthetic episodes with a known, learnable structure (for tests and quick checks)."""
from __future__ import annotations

import numpy as np

from cdrl.data.episode import Episode


def synthetic_episodes(
    num: int, length: int, size: int, seed: int = 0, action_dim: int = 3, pushed: bool = True
) -> list[Episode]:
    """Learnable moving shapes: a blob bouncing on its own and (if `pushed`) a blob pushed
    by the actions.

    The first blob moves with a constant velocity and bounces off the edges (predictable
    from two frames); the second moves right by (a_0 - a_1) and down by (a_2 - 0.5), so
    only action-conditioned models can predict it. Actions are uniform in [0, 1].
    Frames are uint8 on a black background.
    """
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    sigma = size / 12
    episodes = []
    for _ in range(num):
        pos = rng.uniform(0.2, 0.8, 2) * size
        vel = rng.choice([-1, 1], 2) * rng.uniform(0.05, 0.09, 2) * size
        push = rng.uniform(0.3, 0.7, 2) * size
        actions = rng.uniform(0, 1, (length, action_dim)).astype(np.float32)
        frames = np.empty((length, size, size), np.uint8)
        for t in range(length):
            blob = np.exp(-((xx - pos[1]) ** 2 + (yy - pos[0]) ** 2) / (2 * sigma**2))
            other = 0.6 * pushed * np.exp(-((xx - push[1]) ** 2 + (yy - push[0]) ** 2) / (2 * sigma**2))
            frames[t] = np.round(255 * np.clip(blob + other, 0, 1))
            pos = pos + vel
            for d in range(2):
                if not 0 <= pos[d] <= size - 1:
                    vel[d] = -vel[d]
                    pos[d] = np.clip(pos[d], 0, size - 1)
            step = np.array([actions[t, 2] - 0.5, actions[t, 0] - actions[t, 1]])
            push = np.clip(push + 0.08 * size * step, 0, size - 1)
        episodes.append(Episode(frames, actions, np.zeros(length, np.float32)))
    return episodes
