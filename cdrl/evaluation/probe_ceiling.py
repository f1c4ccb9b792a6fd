"""What the imagination probe could reach: its ranking with the game's own rewards and values.

The probe (`cdrl.evaluation.imagination_probe`) scores each steering sequence by H imagined
rewards plus γ^H times the value after step H. It asks whether that names the sequence whose real
15-step return is highest. A perfect model imagines the real rewards. A perfect value gives the
expected discounted return of the policy it was fitted to. `ceiling` plays both out in the game,
from the probe's own start states: each sequence held for H steps, then `policy` for `steps`
more, `samples` times. Its ranking is the best any model and value of that policy could score.

Keys: the followed play and the held steps use the probe's keys, so the starts and the real
returns are the probe's. The continuations from one start share their keys (`fold_in(key, 2)`,
split over the samples, then over the steps): every sequence and H meets the same randomness.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from cdrl.evaluation import imagination_probe as ip
from envs.policies import Policy, get_policy, privileged_policy, random_turns_instead

CEILING_HORIZONS = (1, 3, 5)  # the held steps before the value, as the probe's H <= 5
SAMPLES = 8  # the continuations averaged into one value
STEPS = 50  # the continuation's steps (γ 0.9: the steps after hold 0.5 % of the weight)


def continuation_policy(game, name: str) -> Policy:
    """The policy the value follows: a blind one of `envs.policies`, or 'privileged' (the probe's
    followed play: the privileged policy, a share `ip.EXPLORE` of its steps random turns)."""
    return privileged_policy(game) if name == "privileged" else get_policy(name)


def _act(policy: Policy, env_params, explore: float):
    """`act(key, policy_state, game_state) -> (buttons, policy_state)`; blind policies see no frame."""
    def act(key, ps, state):
        if not policy.privileged:
            return policy.step(key, ps, None)
        k_policy, k_explore = jax.random.split(key)
        label, ps = policy.step(k_policy, ps, None, state, env_params)
        return random_turns_instead(k_explore, label, explore), ps

    return act


def policy_value(game, env_params, policy: Policy, gamma, key, states, on, *, samples: int, steps: int):
    """The value of `policy` at each of the game states `states` (leading axis N; `on` `[N]`:
    the game still on there): the mean over `samples` of its discounted return over `steps`
    steps, `[N]`. Sample i plays from every state with the same keys (`split(key, samples)[i]`,
    split into the policy's init key and the steps' keys; each step's into action and game)."""
    act = _act(policy, env_params, ip.EXPLORE)
    discounts = gamma ** jnp.arange(steps, dtype=jnp.float32)

    def sampled(key, state, on):
        k_init, k_run = jax.random.split(key)

        def body(c, k):
            state, on, ps = c
            k_act, k_env = jax.random.split(k)
            a, ps = act(k_act, ps, state)
            state, reward, term, trunc, _ = game.step_state(k_env, state, a, env_params)
            return (state, on & ~(term | trunc), ps), reward * on

        rewards = jax.lax.scan(body, (state, on, policy.init(k_init)), jax.random.split(k_run, steps))[1]
        return rewards @ discounts

    per_sample = jax.vmap(lambda k: jax.vmap(sampled, (None, 0, 0))(k, states, on))(jax.random.split(key, samples))
    return per_sample.mean(0)


@functools.partial(jax.jit, static_argnames=("game", "policy", "points", "every", "horizon", "horizons",
                                             "samples", "steps"))
def _branches(game, env_params, policy: Policy, gamma, keys, *, points: int, every: int, horizon: int,
              horizons: tuple, samples: int, steps: int):
    buttons = jnp.asarray(list(ip.SEQUENCES.values()), jnp.float32)
    n = buttons.shape[0]

    def followed(c, _):  # imagination_probe.follow_step's game, without the model: the same keys
        state, key, alive = c
        key, k_policy, k_explore, k_env = jax.random.split(key, 4)
        label, _ = privileged_policy(game).step(k_policy, None, None, state, env_params)
        executed = random_turns_instead(k_explore, label, ip.EXPLORE)
        state, _, term, trunc, _ = game.step_state(k_env, state, executed, env_params)
        return (state, key, alive & ~(term | trunc)), None

    def held(key, state):  # imagination_probe's real branches, the state after every step kept
        def body(c, k):
            state, on = c
            state, reward, term, trunc, _ = jax.vmap(game.step_state, (None, 0, 0, None))(k, state, buttons,
                                                                                        env_params)
            after = on & ~(term | trunc)
            return (state, after), (reward * on, state, after)

        states = jax.tree.map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), state)
        return jax.lax.scan(body, (states, jnp.ones(n, bool)), jax.random.split(key, horizon))[1]

    def mean_value(key, state, on):  # [n] sequences' states -> [n]
        return policy_value(game, env_params, policy, gamma, key, state, on, samples=samples, steps=steps)

    def block(c, _):
        c = jax.lax.scan(followed, c, None, length=every)[0]
        state, key, on = c
        rewards, states, after = held(jax.random.fold_in(key, 1), state)
        k_value = jax.random.fold_in(key, 2)
        values = jnp.stack([mean_value(k_value, jax.tree.map(lambda x: x[h - 1], states), after[h - 1])
                            for h in horizons])
        return c, (rewards, values, on)

    def one(key):
        k_reset, k_run = jax.random.split(key)
        state = game.reset_state(k_reset, env_params)
        return jax.lax.scan(block, (state, k_run, jnp.array(True)), None, length=points)[1]

    return jax.vmap(one)(keys)


def branches(game, env_params, policy: Policy, gamma: float, *, games: int, points: int, every: int,
             horizon: int = ip.HORIZON, horizons=CEILING_HORIZONS, samples: int = SAMPLES,
             steps: int = STEPS) -> dict:
    """The probe's starts (`games` games from seed `ip.GAME_SEED`, `points` starts every `every`
    steps) as numpy arrays: `real` rewards `[games, points, sequences, horizon]` (the probe's),
    `value` `[games, points, len(horizons), sequences]` (the mean over `samples` of `policy`'s
    discounted return over `steps` steps after the sequence's first H steps) and `alive`
    `[games, points]` (the game on at the start)."""
    keys = jax.vmap(jax.random.PRNGKey)(ip.GAME_SEED + jnp.arange(games))
    rewards, values, alive = _branches(game, env_params, policy, jnp.float32(gamma), keys, points=points,
                                       every=every, horizon=horizon, horizons=tuple(horizons), samples=samples,
                                       steps=steps)
    return {"real": np.moveaxis(np.asarray(rewards), 2, 3), "value": np.asarray(values), "alive": np.asarray(alive)}


def ceiling(game, env_params, policy: str | Policy, gamma: float, *, max_steps: int, games: int = 32,
            every: int = 10, horizons=CEILING_HORIZONS, samples: int = SAMPLES, steps: int = STEPS) -> dict:
    """The probe's ranking figures (`ip.rank_scores`) against the real `ip.HORIZON`-step return,
    per H in `horizons`: `rewards_only[H]`, a sequence scored by its real first H rewards (a
    perfect model, no value); `with_value[H]`, those plus γ^H times `policy`'s value after step
    H (a perfect model and a perfect value of `policy`). `mean_value[H]`: that value per sequence,
    averaged over the starts."""
    if games < 1 or every < 1 or max_steps // every < 2:
        raise ValueError(f"{games} games with a start every {every} steps of {max_steps} leave no start")
    if not horizons or min(horizons) < 1 or max(horizons) > ip.HORIZON:
        raise ValueError(f"the held steps H must lie in 1 .. {ip.HORIZON}; got {tuple(horizons)}")
    if samples < 1 or steps < 1:
        raise ValueError(f"the value needs at least one sample of one step; got {samples} samples of {steps}")
    pol = continuation_policy(game, policy) if isinstance(policy, str) else policy
    b = branches(game, env_params, pol, gamma, games=games, points=max_steps // every - 1, every=every,
                 horizons=horizons, samples=samples, steps=steps)
    alive = b["alive"]
    real, values = b["real"][alive], b["value"][alive]
    total = real.sum(-1)
    out = {"policy": pol.name, "gamma": gamma, "samples": samples, "steps": steps, "starts": int(alive.sum()),
           "rewards_only": {}, "with_value": {}, "mean_value": {}}
    for i, h in enumerate(horizons):
        first = real[..., :h].sum(-1)
        out["rewards_only"][str(h)] = ip.rank_scores(total, first)
        out["with_value"][str(h)] = ip.rank_scores(total, first + gamma ** h * values[:, i])
        out["mean_value"][str(h)] = values[:, i].mean(0).tolist()
    return out


def attribution(imagined: np.ndarray, values: np.ndarray, real: np.ndarray, played: np.ndarray, gamma: float,
                horizons=CEILING_HORIZONS) -> dict:
    """Which half of a model's look-ahead loses the ranking: per H in `horizons`, the probe's
    `ip.rank_scores` with a sequence scored by H rewards plus γ^H times a value at step H, each
    half the model's or the game's. From the probe's arrays on its starts (`imagined`, `real`
    `[N, sequences, horizon]` rewards, `values` `[N, sequences, horizon]` the model's value after
    each step) and `played` `[N, len(horizons), sequences]` (the played-out value, `branches`):
    `model` (both the model's: the probe's `by_horizon`), `game_rewards` (the game's rewards,
    the model's value), `game_value` (the model's rewards, the played-out value) and `game`
    (both the game's: `ceiling`'s `with_value`)."""
    total = real.sum(-1)
    out = {name: {} for name in ("model", "game_rewards", "game_value", "game")}
    for i, h in enumerate(horizons):
        rewards = {"model": imagined[..., :h].sum(-1), "game": real[..., :h].sum(-1)}
        value = {"model": values[..., h - 1], "game": played[:, i]}
        for name, (r, v) in {"model": ("model", "model"), "game_rewards": ("game", "model"),
                             "game_value": ("model", "game"), "game": ("game", "game")}.items():
            out[name][str(h)] = ip.rank_scores(total, rewards[r] + gamma ** h * value[v])
    return out
