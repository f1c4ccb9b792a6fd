"""Playing whole episodes with a policy, many games at once, and the return table.

A policy is `init(key) -> state` and `step(key, state, obs) -> (action, state)` for one
game (the form of `envs.policies`; a privileged policy's step also takes the game's state and
physics); `play` runs N games in one `vmap` and a `lax.scan` of `max_steps`, and counts each
game's return and length up to its first episode end. A learned policy takes its parameters as
an argument, `init(key, params)` and `step(key, state, obs, params)`, passed traced (`play(...,
params=)`), so one compiled program plays it at every evaluation of a run: `controller_policy`
gives a trained controller variant so, without exploration noise (it executes ã_t and feeds it
back, as in training), `cdrl.learners.ppo.ppo_policy` a PPO policy.

`compare_policies` is the protocol every figure of control uses: the learned policies and the
reference policies (`REFERENCES`: uniform random, random turning that never accelerates, the
thesis's behaviour switching, and the privileged scripted policy) on the same held-out games,
seeds `EVAL_SEED`, `EVAL_SEED` + 1, ..., each at most `max_steps` steps.
"""
from __future__ import annotations

import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats

from cdrl.data.frames import copy_last_bce, model_obs, pixel_bce, target_entropy
from cdrl.evaluation.metrics import excess_ratio
from cdrl.models.base import StepInput, Variant


@functools.lru_cache(maxsize=32)
def controller_fns(variant: Variant) -> tuple[Callable, Callable]:
    """(init, step) of a controller variant's noise-free policy for one game, its parameters an
    argument: `init(key, params)`, `step(key, state, obs, params)`. One pair per variant, so a
    program playing it compiles once for any parameters (they are traced, not baked in)."""

    def init(key, params):
        del key, params
        return {"carry": variant.init_carry(1), "action": jnp.zeros((1, variant.arch.action_dim)),
                "is_first": jnp.ones((1,), bool)}

    def step(key, state, obs, params):
        del key
        x = StepInput(obs=model_obs(obs, variant.arch)[None], action=state["action"], is_first=state["is_first"])
        carry, out = variant.step(params, state["carry"], x)
        new = {"carry": carry, "action": out["action"], "is_first": jnp.zeros((1,), bool)}
        return state["action"][0], new

    return init, step


def controller_policy(variant: Variant, params) -> tuple[Callable, Callable, Any]:
    """The trained controller as a noise-free policy: `(init, step, params)` for `play`
    (`params=`) and `compare_policies`. It executes ã_t and feeds it back, as in training."""
    return (*controller_fns(variant), params)


EVAL_SEED = 10_000  # the first held-out game; training games never use seeds this high
# The first test game: final figures only, never a choice (validation games start at EVAL_SEED).
TEST_SEED = 30_000
REFERENCES = ("uniform", "never_accelerate", "behaviour", "privileged")


@functools.partial(jax.jit, static_argnums=(0, 1, 2, 5, 6))
def _play(game, policy_init, policy_step, env_params, keys, max_steps: int, privileged: bool, params):
    # A learned policy's parameters come in traced (`params`), a reference policy has none.
    learned = params is not None
    init = functools.partial(policy_init, params=params) if learned else policy_init

    def one_game(key):
        k_reset, k_policy, k_run = jax.random.split(key, 3)
        obs, env_state = game.reset(k_reset, env_params)

        def body(c, _):
            env_state, obs, pstate, key, ret, length, alive = c
            key, k_act, k_env = jax.random.split(key, 3)
            if privileged:
                action, pstate = policy_step(k_act, pstate, obs, env_state, env_params)
            elif learned:
                action, pstate = policy_step(k_act, pstate, obs, params)
            else:
                action, pstate = policy_step(k_act, pstate, obs)
            obs, env_state, reward, term, trunc, _ = game.step(k_env, env_state, action, env_params)
            ret = ret + jnp.where(alive, reward, 0.0)
            length = length + alive.astype(jnp.int32)
            alive = alive & ~(term | trunc)
            return (env_state, obs, pstate, key, ret, length, alive), None

        c0 = (env_state, obs, init(k_policy), k_run, jnp.zeros(()), jnp.zeros((), jnp.int32), jnp.array(True))
        c, _ = jax.lax.scan(body, c0, None, length=max_steps)
        return c[4], c[5]

    return jax.vmap(one_game)(keys)


def play(game, env_params, policy_init, policy_step, seeds: list[int] | np.ndarray, max_steps: int,
         privileged: bool = False, params=None):
    """Returns and lengths `[N]` of one episode per seed (at most `max_steps` steps each);
    `privileged`: the policy's step takes the game's state and physics too; `params`: a learned
    policy's parameters, passed to `init(key, params)` and `step(key, state, obs, params)`."""
    keys = jax.vmap(jax.random.PRNGKey)(jnp.asarray(seeds))
    returns, lengths = _play(game, policy_init, policy_step, env_params, keys, int(max_steps), privileged, params)
    return np.asarray(returns), np.asarray(lengths)


def reference_policy(game, name: str):
    """The reference policy `name` (one of `REFERENCES`) of `game`."""
    from envs.policies import get_policy, privileged_policy

    if name not in REFERENCES:
        raise ValueError(f"unknown reference policy {name!r}; choose one of {', '.join(REFERENCES)}")
    return privileged_policy(game) if name == "privileged" else get_policy(name)


def compare_policies(game, env_params, learned: dict[str, tuple], episodes: int,
                     max_steps: int, seed: int = EVAL_SEED, references: bool = True) -> dict[str, dict]:
    """The `learned` policies (name -> (init, step) in the form of `envs.policies`, or
    (init, step, params) as `controller_policy` gives them; noise-free) and, with `references`,
    every reference policy, on the same `episodes` held-out games: name -> `summarize` row."""
    seeds = np.arange(seed, seed + episodes)
    rows = {name: summarize(*play(game, env_params, policy[0], policy[1], seeds, max_steps,
                                  params=policy[2] if len(policy) == 3 else None))
            for name, policy in learned.items()}
    for name in REFERENCES if references else ():
        policy = reference_policy(game, name)
        rows[name] = summarize(*play(game, env_params, policy.init, policy.step, seeds, max_steps,
                                     privileged=policy.privileged))
    return rows


@functools.partial(jax.jit, static_argnums=(0, 1, 5))
def _model_trace(variant: Variant, game, params, env_params, keys, max_steps: int):
    """Per game and step `[N, T]`: the controller's predicted reward r̃_{t+1}, the real r_{t+1},
    whether the game was still on, and on the frames the BCE of the predicted õ_{t+1}, of
    copying o_t, and the floor (the target's entropy)."""
    def one_game(key):
        k_reset, k_run = jax.random.split(key)
        obs, env_state = game.reset(k_reset, env_params)

        def body(c, _):
            env_state, obs, pstate, key, alive = c
            key, k_env = jax.random.split(key)
            x = StepInput(obs=model_obs(obs, variant.arch)[None], action=pstate["action"],
                          is_first=pstate["is_first"])
            carry, out = variant.step(params, pstate["carry"], x)
            pstate = {"carry": carry, "action": out["action"], "is_first": jnp.zeros((1,), bool)}
            obs, env_state, reward, term, trunc, _ = game.step(k_env, env_state, x.action[0], env_params)
            target = model_obs(obs, variant.arch)[None]
            frames = (pixel_bce(out["logits"], target)[0], copy_last_bce(x.obs, target)[0], target_entropy(target)[0])
            return (env_state, obs, pstate, key, alive & ~(term | trunc)), (out["reward"][0], reward, alive, *frames)

        c0 = (env_state, obs, controller_fns(variant)[0](None, params), k_run, jnp.array(True))
        return jax.lax.scan(body, c0, None, length=max_steps)[1]

    return jax.vmap(one_game)(keys)


def model_fit(variant: Variant, params, game, env_params, seeds, max_steps: int) -> dict[str, float]:
    """How well a controller variant's world model predicts its own noise-free play on the
    held-out games `seeds`, over every step played: the reward head's correlation of r̃_{t+1}
    with r_{t+1} and R² = 1 - MSE / variance of r (0: no better than the mean reward), and the
    next-frame `excess_ratio` (BCE - floor) / (copy-last BCE - floor) of its predicted frames."""
    keys = jax.vmap(jax.random.PRNGKey)(jnp.asarray(seeds))
    trace = [np.asarray(x) for x in _model_trace(variant, game, params, env_params, keys, int(max_steps))]
    pred, real, alive = trace[:3]
    bce, copy, floor = (float(x[alive].astype(np.float64).mean()) for x in trace[3:])
    pred, real = pred[alive].astype(np.float64), real[alive].astype(np.float64)
    var = float(np.var(real))
    corr = float(np.corrcoef(pred, real)[0, 1]) if np.std(pred) > 0 and var > 0 else float("nan")
    r2 = 1.0 - float(np.mean(np.square(pred - real))) / var if var > 0 else float("nan")
    return {"correlation": corr, "r2": r2, "steps": int(alive.sum()), "mean_predicted": float(pred.mean()),
            "mean_real": float(real.mean()), "excess_ratio": excess_ratio(bce, copy, floor)}


def summarize(returns: np.ndarray, lengths: np.ndarray) -> dict[str, Any]:
    """Mean return with a 95 % confidence interval (Student t), mean episode length."""
    n = len(returns)
    mean = float(np.mean(returns))
    half = float(scipy.stats.t.ppf(0.975, n - 1) * np.std(returns, ddof=1) / np.sqrt(n)) if n > 1 else float("nan")
    return {"mean_return": mean, "ci95": [mean - half, mean + half], "episodes": n,
            "mean_length": float(np.mean(lengths))}


def format_table(rows: dict[str, dict]) -> str:
    lines = [f"{'policy':24s} {'mean return':>12s} {'95% CI':>22s} {'length':>8s} {'episodes':>9s}"]
    for name, r in rows.items():
        lo, hi = r["ci95"]
        lines.append(f"{name:24s} {r['mean_return']:12.3f} [{lo:9.3f}, {hi:9.3f}] {r['mean_length']:8.1f} {r['episodes']:9d}")
    return "\n".join(lines)
