"""Online training of the controller variants against the built-in game, as one program.

One `online_step` is a jitted function: a `lax.scan` over T steps in which the model acts
(its controller output ã is executed, with exploration noise) and the B games (`vmap`)
answer; then the loss, the gradients and the optimiser update. The games' outputs enter the graph
behind a stop-gradient (the game is not differentiable; the model's predictions are), and
the model's own action output keeps its gradient as it is fed back (straight-through past
the exploration noise and the clip to [0, 1]).

Objective: observation BCE + reward_weight * reward MSE − ascent * mean predicted reward.
The ascent term (gradient ascent on predicted reward through BPTT, the thesis's future work)
is switched on after `warmup_steps`, and may change either the controller D_a only
(`scope="controller"`) or every parameter (`scope="all"`, the thesis's literal wording, which
also lets the model simply predict more reward unless the prediction loss holds it back).
The scope is a traced number, so one compiled program serves both (and a sweep over them).
The predicted reward is summed over the T-step chunk: T is the ascent's horizon.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp

from cdrl.data.frames import copy_last_bce, model_obs, target_entropy
from cdrl.models.base import StepInput, Variant, bce_with_logits
from cdrl.training.optim import OptHParams, init_opt_state
from cdrl.training.step import TrainState, guarded_update, run_once

SCOPES = ("controller", "all")


@dataclasses.dataclass(frozen=True)
class OnlineConfig:
    """Static shape of online training."""

    num_envs: int = 8
    unroll: int = 32

    def __post_init__(self):
        if self.num_envs < 1 or self.unroll < 1:
            raise ValueError(f"num_envs and unroll must be >= 1, got {self.num_envs} and {self.unroll}")


@flax.struct.dataclass
class OnlineHParams:
    """Traced numbers of online training (a `vmap` sweep can vary any of them)."""

    opt: OptHParams  # the optimiser (SGD with momentum by default)
    ascent: jax.Array  # lambda: weight of the reward-ascent term
    reward_weight: jax.Array
    noise_std: jax.Array  # exploration noise on ã when acting
    noise_decay: jax.Array  # per update: std_k = noise_std * noise_decay ** k
    warmup_steps: jax.Array  # updates of pure model learning before the ascent term
    diverge_threshold: jax.Array
    ascent_all: jax.Array  # 1: the ascent may change every parameter ("all"); 0: the controller only

    @classmethod
    def create(cls, lr=0.1, momentum=0.9, ascent=0.1, reward_weight=0.1, noise_std=0.3, noise_decay=0.999,
               warmup_steps=100, diverge_threshold=1e3, scope="controller",
               opt: OptHParams | None = None) -> "OnlineHParams":
        """`opt`: the optimiser's numbers (default: SGD with `lr` and `momentum`, which it
        replaces)."""
        if scope not in SCOPES:
            raise ValueError(f"unknown ascent scope {scope!r}; choose one of {SCOPES}")
        f32 = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
        opt = opt if opt is not None else OptHParams.create(lr=lr, momentum=momentum)
        return cls(opt, f32(ascent), f32(reward_weight), f32(noise_std), f32(noise_decay),
                   f32(warmup_steps), f32(diverge_threshold), f32(scope == "all"))


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


@flax.struct.dataclass
class OnlineState:
    train: TrainState  # params, optimiser state, model carry, update count
    games: Games
    action: jax.Array  # [B, A]: ã_t, the model's output to execute next (keeps no gradient across updates)
    key: jax.Array


def init_online(variant: Variant, game, env_params, cfg: OnlineConfig, key: jax.Array,
                hp: OnlineHParams) -> OnlineState:
    """Fresh parameters, optimiser state, carries and B new games."""
    if not variant.has_controller:
        raise ValueError(f"variant {variant.name!r} has no controller; online training needs one of "
                         "action_loop, reward_prediction, final_proposal")
    return run_once(_init_online, variant, game, env_params, cfg, key, hp, static_argnums=(0, 1, 3))


def _init_online(variant, game, env_params, cfg, key, hp) -> OnlineState:
    k_params, k_env, k_run = jax.random.split(key, 3)
    params = variant.init(k_params)
    b = cfg.num_envs
    train = TrainState(params=params, opt_state=init_opt_state(hp.opt, params),
                       carry=variant.init_carry(b), step=jnp.zeros((), jnp.int32))
    return OnlineState(train=train, games=reset_games(game, env_params, k_env, b, variant.arch),
                       action=jnp.zeros((b, variant.arch.action_dim)), key=k_run)


@flax.struct.dataclass
class Rollout:
    """What a rollout carries from one step to the next: the model's recurrent state, the
    games, ã_t (the model's output, executed next) and the PRNG key."""

    carry: Any
    games: Games
    action: jax.Array
    key: jax.Array


def transition(variant: Variant, game, params, env_params, noise_std, c: Rollout):
    """One step of acting and predicting. Returns (next rollout, (model outputs, game
    statistics)) with the game's outputs stop-gradiented."""
    key, k_noise, k_game = jax.random.split(c.key, 3)
    noisy = jnp.clip(c.action + noise_std * jax.random.normal(k_noise, c.action.shape), 0.0, 1.0)
    a_in = c.action + jax.lax.stop_gradient(noisy - c.action)  # the executed value, gradient to ã
    obs = c.games.obs
    carry, out = variant.step(params, c.carry, StepInput(obs=obs, action=a_in, is_first=c.games.is_first))
    games, nxt, reward, stats = step_games(game, env_params, c.games, noisy, k_game, variant.arch)
    outs = {"logits": out["logits"], "obs": obs, "target": nxt,
            "pred_reward": out["reward"] if variant.predicts_reward else jnp.zeros_like(reward)}
    done = games.is_first
    return Rollout(carry=carry, games=games, action=jnp.where(done[:, None], 0.0, out["action"]), key=key), (outs, stats)


def rollout_carry(state: OnlineState) -> Rollout:
    return Rollout(carry=jax.lax.stop_gradient(state.train.carry), games=state.games, action=state.action,
                   key=state.key)


def chunk_objective(variant: Variant, outs, stats, hp: OnlineHParams):
    """(model loss, mean predicted reward, loss terms) of a chunk's outputs `[T, B, ...]`.
    Besides the weighted terms, `copy_bce` and `target_entropy` (weight 0) score copying the
    last frame and the floor on the same frames, for the excess ratio of the predictions."""
    target = jax.lax.stop_gradient(outs["target"])
    terms = {"obs_bce": bce_with_logits(outs["logits"], target), **copy_scores(outs["obs"], target)}
    if variant.predicts_reward:
        terms["reward_mse"] = jnp.mean(jnp.square(outs["pred_reward"] - stats["reward"]))
    model_loss = terms["obs_bce"] + hp.reward_weight * terms.get("reward_mse", 0.0)
    return model_loss, jnp.mean(outs["pred_reward"]), terms


def _rollout(variant: Variant, game, cfg: OnlineConfig, params, state: OnlineState, hp: OnlineHParams, env_params):
    """Act and predict for T steps. Returns ((model_loss, mean predicted reward), aux)."""
    noise_std = hp.noise_std * hp.noise_decay ** state.train.step.astype(jnp.float32)
    c, (outs, stats) = jax.lax.scan(
        lambda c, _: transition(variant, game, params, env_params, noise_std, c),
        rollout_carry(state), None, length=cfg.unroll)
    model_loss, pred_reward, terms = chunk_objective(variant, outs, stats, hp)
    new_state = state.replace(train=state.train.replace(carry=c.carry), games=c.games,
                              action=jax.lax.stop_gradient(c.action), key=c.key)
    return (model_loss, pred_reward), (new_state, terms, stats, noise_std)


def _add_ascent_rest(variant: Variant, shared, reward, rest):
    """`shared` plus `rest` times `reward` (D_a's groups only) on the controller D_a's parameters;
    `shared` elsewhere."""
    return {k: (jax.tree.map(lambda s, r: s + rest * r, v, reward[k]) if k in variant.controller_groups else v)
            for k, v in shared.items()}


def online_step_fn(variant: Variant, game, cfg: OnlineConfig, state: OnlineState, hp: OnlineHParams, env_params):
    """One chunk of acting, predicting and learning; see the module docstring."""
    params = state.train.params
    (model_loss, pred_reward), vjp, (new_state, terms, stats, noise_std) = jax.vjp(
        lambda p: _rollout(variant, game, cfg, p, state, hp, env_params), params, has_aux=True)
    active = (state.train.step.astype(jnp.float32) >= hp.warmup_steps).astype(jnp.float32)
    lam = hp.ascent * active
    # The gradient of model_loss − lam * pred_reward, the ascent on D_a's parameters only unless
    # `ascent_all`: one backward pass gives every parameter the model's gradient and the ascent's
    # share that reaches all of them (lam * ascent_all); a second adds the rest of the ascent to
    # D_a, and only D_a's gradient is taken from it, so XLA leaves the others' computation out
    # (the kernel gradients and their sums over the chunk's steps). There is no rest before the
    # ascent is on or with `ascent_all`: the second pass is then skipped (under `vmap`, a sweep
    # over the scope or the warm-up, `lax.cond` runs both branches and the pass is always taken).
    rest = -lam * (1.0 - hp.ascent_all)
    (shared,) = vjp((jnp.ones(()), -lam * hp.ascent_all))

    def reward_gradient():
        (reward,) = vjp((jnp.zeros(()), jnp.ones(())))
        return {k: reward[k] for k in variant.controller_groups}

    def no_rest():
        return {k: jax.tree.map(jnp.zeros_like, params[k]) for k in variant.controller_groups}

    reward = jax.lax.cond(rest != 0.0, reward_gradient, no_rest)
    grads = _add_ascent_rest(variant, shared, reward, rest)
    new_params, opt_state, guard = guarded_update(hp.opt, hp.diverge_threshold, params, state.train.opt_state, grads,
                                                  model_loss)
    # A refused update keeps the old parameters; the games go on.
    train = new_state.train.replace(params=new_params, opt_state=opt_state, step=state.train.step + 1)
    out_state = new_state.replace(train=train)
    finished = jnp.sum(stats["done"])
    metrics = {
        "loss": model_loss - lam * pred_reward,
        "terms": {**terms, "pred_reward": pred_reward},
        "reward": jnp.mean(stats["reward"]),
        "episodes": finished,
        "return_sum": jnp.sum(stats["finished_return"]),
        "length_sum": jnp.sum(stats["finished_length"]),
        "action_mean": jnp.mean(stats["action"], axis=(0, 1)),
        "noise_std": noise_std,
        "ascent_on": active,
        **guard,
    }
    return out_state, metrics


online_step = jax.jit(online_step_fn, static_argnums=(0, 1, 2))
