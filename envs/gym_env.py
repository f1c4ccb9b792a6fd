"""gymnasium front ends of the Slither game and the pre-processing wrapper.

* :class:`SlitherEnv` -- one game, ``gymnasium.make("cdrl/Slither-v0")``.
  Observation ``Box(0, 1, (150, 150, 1), float32)`` (the pre-processed image, drawn
  directly by the fast renderer) or, with ``obs_type="rgb"``, the raw frame
  ``Box(0, 255, (300, 500, 3), uint8)``.  Action ``Box(0, 1, (3,), float32)``: turn
  right, turn left, accelerate, each performed when > 0.5.  ``render_mode=
  "rgb_array"`` makes :meth:`SlitherEnv.render` return the raw 500 x 300 frame.
* :class:`SlitherVectorEnv` -- N games stepped by one jitted ``vmap`` call, with
  gymnasium's next-step auto-reset.
* :class:`PreprocessObservation` -- an ``ObservationWrapper`` applying
  :func:`envs.preprocess.preprocess` to any environment with RGB image observations.
"""

from __future__ import annotations

import functools
from typing import Any

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from envs import fastrng
from envs import render as _render
from envs.preprocess import DEFAULT_CROP, DEFAULT_OUT_SIZE, preprocess
from envs.flow_view import make_game
from envs.slither import Slither, SlitherParams, canonical_params


@functools.lru_cache(maxsize=16)
def _game(game_items: tuple[tuple[str, Any], ...]) -> Slither:
    return make_game(**dict(game_items))


def game_for(**game_kwargs: Any) -> Slither:
    """The shared :class:`Slither` instance for these static sizes.

    Environments with equal sizes share one instance, hence one set of compiled
    functions (:attr:`Slither.jit`).
    """
    return _game(tuple(sorted(game_kwargs.items())))


@functools.lru_cache(maxsize=16)
def _vector_step(game: Slither):
    """Jitted step of N games with next-step auto-reset (see SlitherVectorEnv)."""

    def one(key, state, action, restart, params):
        k_step, k_reset = fastrng.split(key)
        stepped, reward, terminated, truncated, _ = game.step_state(k_step, state, action, params)
        fresh = game.reset_state(k_reset, params)
        state = jax.tree.map(lambda a, b: jnp.where(restart, a, b), fresh, stepped)
        no = jnp.zeros((), bool)
        return (
            game.get_obs(state, params),
            state,
            jnp.where(restart, 0.0, reward),
            jnp.where(restart, no, terminated),
            jnp.where(restart, no, truncated),
            state.length[0],
        )

    return jax.jit(jax.vmap(one, in_axes=(0, 0, 0, 0, None)))


def _key(rng: np.random.Generator) -> np.ndarray:
    """A ``PRNGKey``-style uint32[2] key drawn from a numpy generator."""
    return rng.integers(0, 2**32, size=2, dtype=np.uint32)


def _params_with(params: SlitherParams | None, max_steps: int | None) -> SlitherParams:
    params = SlitherParams() if params is None else params
    if max_steps is not None:
        params = params.replace(max_steps=int(max_steps))
    return canonical_params(params)


class SlitherEnv(gym.Env):
    """One Slither game behind the gymnasium API.

    Args:
      render_mode: None or "rgb_array" (render returns the raw [300, 500, 3] frame).
      obs_type: "processed" (the [150, 150, 1] float32 observation) or "rgb" (the raw
        frame as observation, e.g. to apply :class:`PreprocessObservation`).
      params: physics values (default :class:`SlitherParams`).
      max_steps: if given, overrides ``params.max_steps`` (truncation).
      **game_kwargs: static sizes passed to :class:`Slither`.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, render_mode: str | None = None, obs_type: str = "processed",
                 params: SlitherParams | None = None, max_steps: int | None = None,
                 **game_kwargs: Any):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        if obs_type not in ("processed", "rgb"):
            raise ValueError(f"obs_type must be 'processed' or 'rgb', got {obs_type!r}")
        self.render_mode = render_mode
        self.obs_type = obs_type
        self.game = game_for(**game_kwargs)
        self.params = jax.device_put(_params_with(params, max_steps))
        if obs_type == "rgb":
            self.observation_space = gym.spaces.Box(
                0, 255, (_render.RAW_HEIGHT, _render.RAW_WIDTH, 3), np.uint8
            )
        else:
            size = _render.OBS_SIZE
            self.observation_space = gym.spaces.Box(0.0, 1.0, (size, size, 1), np.float32)
        self.action_space = gym.spaces.Box(0.0, 1.0, (3,), np.float32)
        self._state = None

    @property
    def state(self):
        """The current :class:`envs.slither.SlitherState` (None before reset)."""
        return self._state

    def _observe(self, obs, state):
        if self.obs_type == "rgb":
            return np.array(self.game.jit.render_raw(state, self.params))
        return np.array(obs)[..., None]

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        obs, self._state = self.game.jit.reset(_key(self.np_random), self.params)
        return self._observe(obs, self._state), {"length": float(self._state.length[0])}

    def step(self, action):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        action = np.asarray(action, np.float32).reshape(3)
        obs, self._state, reward, terminated, truncated, info = self.game.jit.step(
            _key(self.np_random), self._state, action, self.params
        )
        return (
            self._observe(obs, self._state),
            float(reward),
            bool(terminated),
            bool(truncated),
            {"length": float(info["length"])},
        )

    def render(self):
        if self.render_mode != "rgb_array" or self._state is None:
            return None
        return np.array(self.game.jit.render_raw(self._state, self.params))


class SlitherVectorEnv(VectorEnv):
    """``num_envs`` Slither games stepped together by one jitted ``vmap``-ed call.

    Observations are [num_envs, 150, 150, 1] float32.  Auto-reset follows
    gymnasium's next-step mode: after a step that ends a game (terminated or
    truncated) the next :meth:`step` ignores that game's action, starts a new game
    and returns its first observation with reward 0 and no termination.

    Args:
      num_envs: number of games.
      params: physics values (default :class:`SlitherParams`).
      max_steps: if given, overrides ``params.max_steps``.
      **game_kwargs: static sizes passed to :class:`Slither`.
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}

    def __init__(self, num_envs: int, params: SlitherParams | None = None,
                 max_steps: int | None = None, **game_kwargs: Any):
        self.num_envs = int(num_envs)
        self.game = game_for(**game_kwargs)
        self._step = _vector_step(self.game)
        self.params = jax.device_put(_params_with(params, max_steps))
        size = _render.OBS_SIZE
        self.single_observation_space = gym.spaces.Box(0.0, 1.0, (size, size, 1), np.float32)
        self.single_action_space = gym.spaces.Box(0.0, 1.0, (3,), np.float32)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._states = None
        self._needs_reset = np.zeros((self.num_envs,), bool)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self._np_random, self._np_random_seed = gym.utils.seeding.np_random(int(seed))
        shape = jax.eval_shape(self.game.reset_state, _key(np.random.default_rng(0)), self.params)
        blank = jax.tree.map(lambda a: jnp.zeros((self.num_envs,) + a.shape, a.dtype), shape)
        self._needs_reset = np.ones((self.num_envs,), bool)
        obs, _, _, _, info = self._advance(np.zeros((self.num_envs, 3), np.float32), blank)
        return obs, info

    def step(self, actions):
        if self._states is None:
            raise RuntimeError("call reset() before step()")
        return self._advance(actions, self._states)

    def _advance(self, actions, states):
        actions = np.asarray(actions, np.float32).reshape(self.num_envs, 3)
        keys = self.np_random.integers(0, 2**32, size=(self.num_envs, 2), dtype=np.uint32)
        obs, self._states, reward, terminated, truncated, length = self._step(
            keys, states, actions, self._needs_reset, self.params
        )
        terminated = np.array(terminated)
        truncated = np.array(truncated)
        self._needs_reset = terminated | truncated
        return (
            np.array(obs)[..., None],
            np.array(reward, np.float32),
            terminated,
            truncated,
            {"length": np.array(length)},
        )


class PreprocessObservation(gym.ObservationWrapper):
    """Pre-processes RGB image observations as the thesis did.

    Works on any environment whose observations are [H, W, C] images (uint8 in
    0..255 or float in [0, 1]).  The new observation is [out_h, out_w, 1] float32 in
    [0, 1].

    Args:
      env: the environment to wrap.
      crop: (top, left, height, width) box, None for the whole frame; the default is
        the central 300 x 300 of a 500 x 300 frame (see
        :func:`envs.preprocess.central_crop` for other frame sizes).
      out_size: (height, width) of the result; must divide the crop size.
    """

    def __init__(self, env: gym.Env, crop: tuple[int, int, int, int] | None = DEFAULT_CROP,
                 out_size: tuple[int, int] = DEFAULT_OUT_SIZE):
        super().__init__(env)
        shape = env.observation_space.shape
        if shape is None or len(shape) != 3:
            raise ValueError(f"expected [H, W, C] image observations, got shape {shape}")
        self.crop = crop
        self.out_size = tuple(out_size)
        preprocess(np.zeros(shape, np.uint8), crop=crop, out_size=self.out_size)
        self.observation_space = gym.spaces.Box(0.0, 1.0, self.out_size + (1,), np.float32)

    def observation(self, observation):
        return preprocess(np.asarray(observation), crop=self.crop, out_size=self.out_size)[..., None]
