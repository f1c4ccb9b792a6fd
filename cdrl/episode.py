"""One recorded episode: the unit every episode source yields and every data set stores."""
from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Episode:
    """Observations, the actions taken after them, and the rewards received on arrival.

    frames:  [N, H, W] uint8 (0..255) or float in [0, 1]; observations o_0 .. o_{N-1}
    actions: [N, A] float32 in [0, 1]; a_t is taken after seeing o_t (the last row is unused)
    rewards: [N] float32; r_t is received on arriving at o_t (r_0 = 0)
    """

    frames: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray

    def __post_init__(self):
        f, a, r = self.frames, self.actions, self.rewards
        if f.ndim != 3:
            raise ValueError(f"episode frames must be [N, H, W], got shape {f.shape}")
        n = f.shape[0]
        if a.ndim != 2 or a.shape[0] != n:
            raise ValueError(f"episode actions must be [{n}, A] to match {n} frames, got shape {a.shape}")
        if r.shape != (n,):
            raise ValueError(f"episode rewards must be [{n}] to match {n} frames, got shape {r.shape}")
        if f.dtype != np.uint8:
            if not np.issubdtype(f.dtype, np.floating):
                raise ValueError(f"episode frames must be uint8 or float in [0, 1], got dtype {f.dtype}")
            if not np.all(np.isfinite(f)):
                raise ValueError("episode frames contain NaN or Inf")
            if f.size and (f.min() < 0.0 or f.max() > 1.0):
                raise ValueError(f"float episode frames must lie in [0, 1], got range [{f.min()}, {f.max()}]")
        if not np.all(np.isfinite(a)) or (a.size and (a.min() < 0.0 or a.max() > 1.0)):
            raise ValueError("episode actions must be finite values in [0, 1]")
        if not np.all(np.isfinite(r)):
            raise ValueError("episode rewards contain NaN or Inf")

    def __len__(self) -> int:
        return self.frames.shape[0]
