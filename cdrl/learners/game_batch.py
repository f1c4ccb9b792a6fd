"""B games as a learner plays them: one `vmap` of the built-in game, each game replaced by a new
one as soon as it ends, every frame at the model's size (`cdrl.data.frames.model_obs`).

The games are not differentiable: what they return enters a learner's graph behind a
stop-gradient.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import flax.struct
import jax
import jax.numpy as jnp

from cdrl.data.frames import copy_last_bce, model_obs, target_entropy


class Observation(NamedTuple):
    """What a learner sees of B games at one step: the frames `[B, S, S]` and which of them
    start an episode `[B]` (an action pending from the episode before is then void)."""

    frames: jax.Array
    is_first: jax.Array


@flax.struct.dataclass
class Games:
    """B games as a learner sees them: their states, the frames o_t the model sees next, which
    of them start an episode, and the running return and length of the current episodes."""

    env_state: Any  # [B] games
    obs: jax.Array  # [B, S, S] at the model's size
    is_first: jax.Array  # [B]
    episode_return: jax.Array  # [B]
    episode_length: jax.Array  # [B]


def reset_games(game, env_params, key, n: int, arch) -> Games:
    """`n` new games, their first frames as a model of architecture `arch` sees them (`model_obs`)."""
    obs, env_state = jax.vmap(game.reset, in_axes=(0, None))(jax.random.split(key, n), env_params)
    return Games(env_state=env_state, obs=model_obs(obs, arch), is_first=jnp.ones((n,), bool),
                 episode_return=jnp.zeros((n,)), episode_length=jnp.zeros((n,), jnp.int32))


def step_games(game, env_params, games: Games, executed: jax.Array, key, arch):
    """Every game one step on the `executed` actions `[B, A]`; a game that ends is replaced by
    a new one at once, every frame as a model of architecture `arch` sees it (`model_obs`).
    Returns (games after the step, the frames o_{t+1} the step led to, the rewards r_{t+1},
    statistics `reward`, `done`, `finished_return`, `finished_length` and `action`). What the
    game returns carries no gradient: it is not differentiable."""
    k_env, k_reset = jax.random.split(key)
    executed = jax.lax.stop_gradient(executed)
    nxt, env_state, reward, term, trunc, _ = jax.vmap(game.step, in_axes=(0, 0, 0, None))(
        jax.random.split(k_env, executed.shape[0]), games.env_state, executed, env_params)
    nxt = jax.lax.stop_gradient(model_obs(nxt, arch))
    reward = jax.lax.stop_gradient(reward.astype(jnp.float32))
    done = term | trunc
    ret, length = games.episode_return + reward, games.episode_length + 1

    def pick(f, s):
        return jnp.where(done.reshape(done.shape + (1,) * (s.ndim - 1)), f, s)

    def restart(_):
        fresh = reset_games(game, env_params, k_reset, executed.shape[0], arch)
        return jax.tree.map(pick, fresh.env_state, env_state), pick(fresh.obs, nxt)

    # New games are drawn and drawn on screen only on the steps where one ends (a few in a
    # hundred): the same values, without a second game's work on every step. (Under a `vmap`
    # over runs the condition is batched and both branches run, as before.)
    env_state, obs = jax.lax.cond(jnp.any(done), restart, lambda _: (env_state, nxt), None)
    after = Games(env_state=env_state, obs=obs, is_first=done,
                  episode_return=jnp.where(done, 0.0, ret), episode_length=jnp.where(done, 0, length))
    stats = {"reward": reward, "done": done, "finished_return": jnp.where(done, ret, 0.0),
             "finished_length": jnp.where(done, length, 0), "action": executed}
    return after, nxt, reward, stats


def copy_scores(obs: jax.Array, target: jax.Array) -> dict[str, jax.Array]:
    """Copying the last frame and the floor on a chunk's frames `[T, B, S, S]` (o_t -> o_{t+1}):
    the `copy_bce` and `target_entropy` terms (weight 0) beside a model's `obs_bce`, for the
    excess ratio of its predictions."""
    target = jax.lax.stop_gradient(target)
    return {"copy_bce": jnp.mean(copy_last_bce(jax.lax.stop_gradient(obs), target)),
            "target_entropy": jnp.mean(target_entropy(target))}


def observe(games: Games) -> Observation:
    """The games' current frames and episode starts."""
    return Observation(frames=games.obs, is_first=games.is_first)
