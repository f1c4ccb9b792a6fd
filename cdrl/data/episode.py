"""One recorded episode: the unit every episode source yields and every data set stores."""
from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Episode:
    """Observations, the actions taken after them, and the rewards received on arrival.

    frames:  [N, H, W] uint8 (0..255) or float32 in [0, 1]; observations o_0 .. o_{N-1}
    actions: [N, A] float32 in [0, 1] (A = 3 for the built-in game); a_t is taken after
             seeing o_t (the last row is unused)
    rewards: [N] float32; r_t is received on arriving at o_t (r_0 = 0)
    """

    frames: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray

    def __post_init__(self):
        f, a, r = self.frames, self.actions, self.rewards
        for name, arr in (("frames", f), ("actions", a), ("rewards", r)):
            if not isinstance(arr, np.ndarray):
                raise ValueError(f"Episode.{name} must be a numpy array, got {type(arr).__name__}")
        if f.ndim != 3:
            raise ValueError(f"Episode.frames must be [N, H, W], got shape {f.shape}")
        n = f.shape[0]
        if n < 1:
            raise ValueError("Episode.frames is empty (an episode has at least one frame)")
        if f.dtype == np.float32:
            if not np.all(np.isfinite(f)):
                raise ValueError("Episode.frames contain NaN or Inf")
            if f.min() < 0.0 or f.max() > 1.0:
                raise ValueError(f"float Episode.frames must lie in [0, 1], got range [{f.min()}, {f.max()}]")
        elif f.dtype != np.uint8:
            raise ValueError(f"Episode.frames must be uint8 or float32, got {f.dtype}")
        if a.ndim != 2 or a.shape[0] != n or a.shape[1] < 1:
            raise ValueError(f"Episode.actions must be [N={n}, A], got shape {a.shape}")
        if a.dtype != np.float32:
            raise ValueError(f"Episode.actions must be float32, got {a.dtype}")
        if not np.all(np.isfinite(a)) or a.min() < 0.0 or a.max() > 1.0:
            raise ValueError("Episode.actions values must be finite and in [0, 1]")
        if r.shape != (n,):
            raise ValueError(f"Episode.rewards must be [N={n}], got shape {r.shape}")
        if r.dtype != np.float32:
            raise ValueError(f"Episode.rewards must be float32, got {r.dtype}")
        if not np.all(np.isfinite(r)):
            raise ValueError("Episode.rewards must be finite")

    def __len__(self) -> int:
        return int(self.frames.shape[0])
