"""Feeding episodes to the trainer: aligned T-step chunks of B independent streams.

An episode source is any sequence of `Episode`s (`len` and integer indexing): a list in
memory, `cdrl.data.synthetic` episodes, or an on-disk data set (`cdrl.data.store`) that
loads one episode at a time.
Each of the B streams walks its own share of the episodes (stream b takes every B-th
episode of a seeded shuffle, epoch after epoch); its transitions (o_t, a_t, o_{t+1},
r_{t+1}) are cut into consecutive chunks of T steps. When an episode ends inside a chunk
the stream goes on with its next episode and marks the step `is_first`, so the model's
carry resets there. The stream's position is a small cursor (`state_dict`) for exact resume.
"""
from __future__ import annotations

from typing import Sequence

import flax.struct
import jax
import numpy as np

from cdrl.data.episode import Episode


@flax.struct.dataclass
class Chunk:
    """T time steps of B streams, time-major. Frames are uint8 (0..255) or float in [0, 1]."""

    obs: jax.Array  # [T, B, H, W]
    next_obs: jax.Array  # [T, B, H, W]: the frame to predict, o_{t+1}
    action: jax.Array  # [T, B, A]: a_t
    reward: jax.Array  # [T, B]: r_{t+1}, received on arriving at o_{t+1}
    is_first: jax.Array  # [T, B] bool
    # [T, B] bool: o_{t+1} is the last frame of an episode its step limit cut, not the game's end
    # (a value bootstraps there); None: every episode ended in the game
    truncated: jax.Array | None = None


class ChunkStream:
    """Yields `Chunk`s of numpy arrays `[T, B, ...]` from an episode source, forever. With
    `step_limit`, an episode of that many steps or more ended at the limit, not in the game:
    its last step is marked `truncated`."""

    def __init__(
        self,
        episodes: Sequence[Episode],
        batch: int,
        unroll: int,
        image_size: int | None = None,
        action_dim: int = 3,
        seed: int = 0,
        shuffle: bool = True,
        step_limit: int | None = None,
    ):
        if unroll < 1:
            raise ValueError(f"unroll length T must be >= 1, got {unroll}")
        if batch < 1:
            raise ValueError(f"batch size B must be >= 1, got {batch}")
        if len(episodes) == 0:
            raise ValueError("the episode source is empty")
        self.episodes, self.batch, self.unroll = episodes, batch, unroll
        self.image_size, self.action_dim = image_size, action_dim
        self.seed, self.shuffle = seed, shuffle
        self.step_limit = step_limit  # an episode of this many steps was cut by the limit
        self.slot = np.arange(batch, dtype=np.int64)  # index into the endless episode order
        self.pos = np.zeros(batch, dtype=np.int64)  # next transition within that episode
        self._perms: dict[int, np.ndarray] = {}
        self._cache: dict[int, Episode] = {}

    # ---- cursor
    def state_dict(self) -> dict:
        return {"slot": self.slot.tolist(), "pos": self.pos.tolist(), "seed": self.seed}

    def load_state_dict(self, state: dict) -> None:
        if len(state["slot"]) != self.batch:
            raise ValueError(f"stream cursor is for {len(state['slot'])} streams, this stream has {self.batch}")
        self.slot = np.asarray(state["slot"], np.int64)
        self.pos = np.asarray(state["pos"], np.int64)
        self.seed = int(state["seed"])

    # ---- episodes
    def _episode_index(self, slot: int) -> int:
        n = len(self.episodes)
        epoch, i = divmod(int(slot), n)
        if not self.shuffle:
            return i
        if epoch not in self._perms:
            if len(self._perms) > 4:
                self._perms.pop(min(self._perms))
            self._perms[epoch] = np.random.default_rng([self.seed, epoch]).permutation(n)
        return int(self._perms[epoch][i])

    def _episode(self, index: int) -> Episode:
        if index not in self._cache:
            if len(self._cache) >= 2 * self.batch:
                self._cache.pop(next(iter(self._cache)))
            self._cache[index] = self._check(index, self.episodes[index])
        return self._cache[index]

    def _check(self, index: int, ep: Episode) -> Episode:
        if len(ep) < 2:
            raise ValueError(f"episode {index} has {len(ep)} frame(s); at least 2 are needed for one transition")
        h, w = ep.frames.shape[1:]
        if self.image_size is not None and (h, w) != (self.image_size, self.image_size):
            raise ValueError(
                f"episode {index} has frames of {h}x{w}, the model expects "
                f"{self.image_size}x{self.image_size}"
            )
        if ep.actions.shape[1] != self.action_dim:
            raise ValueError(f"episode {index} has {ep.actions.shape[1]} action values, expected {self.action_dim}")
        return ep

    # ---- chunks
    def next_chunk(self) -> Chunk:
        T, B = self.unroll, self.batch
        first = self._episode(self._episode_index(self.slot[0]))
        h, w = first.frames.shape[1:]
        obs = np.empty((T, B, h, w), first.frames.dtype)
        nxt = np.empty_like(obs)
        action = np.empty((T, B, self.action_dim), np.float32)
        reward = np.empty((T, B), np.float32)
        is_first = np.zeros((T, B), bool)
        truncated = np.zeros((T, B), bool)
        for b in range(B):
            t = 0
            while t < T:
                ep = self._episode(self._episode_index(self.slot[b]))
                p = int(self.pos[b])
                n = min(T - t, len(ep) - 1 - p)
                if ep.frames.dtype != obs.dtype:
                    raise ValueError(f"episodes mix frame dtypes {ep.frames.dtype} and {obs.dtype}")
                obs[t : t + n, b] = ep.frames[p : p + n]
                nxt[t : t + n, b] = ep.frames[p + 1 : p + 1 + n]
                action[t : t + n, b] = ep.actions[p : p + n]
                reward[t : t + n, b] = ep.rewards[p + 1 : p + 1 + n]
                is_first[t, b] = p == 0
                t += n
                if p + n == len(ep) - 1:
                    truncated[t - 1, b] = self.step_limit is not None and len(ep) - 1 >= self.step_limit
                    self.slot[b] += B
                    self.pos[b] = 0
                else:
                    self.pos[b] = p + n
        return Chunk(obs=obs, next_obs=nxt, action=action, reward=reward, is_first=is_first, truncated=truncated)

    def __iter__(self):
        while True:
            yield self.next_chunk()
