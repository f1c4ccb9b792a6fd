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

from cdrl.data.frames import copy_last_bce, resize_obs, target_entropy
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
class OnlineState:
    train: TrainState  # params, optimiser state, model carry, update count
    env_state: Any  # [B] games
    obs: jax.Array  # [B, H, W]: o_t, what the model sees next
    action: jax.Array  # [B, A]: ã_t, the model's output to execute next (keeps no gradient across updates)
    is_first: jax.Array  # [B]
    key: jax.Array
    episode_return: jax.Array  # [B] running return of the current episodes
    episode_length: jax.Array  # [B]


def _reset_games(game, env_params, key, n: int, size: int):
    obs, env_state = jax.vmap(game.reset, in_axes=(0, None))(jax.random.split(key, n), env_params)
    return resize_obs(obs, size), env_state


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
    obs, env_state = _reset_games(game, env_params, k_env, cfg.num_envs, variant.arch.image_size)
    b = cfg.num_envs
    train = TrainState(params=params, opt_state=init_opt_state(hp.opt, params),
                       carry=variant.init_carry(b), step=jnp.zeros((), jnp.int32))
    return OnlineState(train=train, env_state=env_state, obs=obs, action=jnp.zeros((b, variant.arch.action_dim)),
                       is_first=jnp.ones((b,), bool), key=k_run, episode_return=jnp.zeros((b,)),
                       episode_length=jnp.zeros((b,), jnp.int32))


def transition(variant: Variant, game, params, env_params, noise_std, c):
    """One step of acting and predicting on the rollout carry `c`.

    `c` = (model carry, games, o_t, ã_t, is_first, key, episode returns, episode lengths).
    Returns (next c, (model outputs, game statistics)) with the game's outputs stop-gradiented.
    """
    size = variant.arch.image_size
    model_carry, env_state, obs, action, is_first, key, ep_ret, ep_len = c
    key, k_noise, k_env, k_reset = jax.random.split(key, 4)
    noisy = jnp.clip(action + noise_std * jax.random.normal(k_noise, action.shape), 0.0, 1.0)
    a_in = action + jax.lax.stop_gradient(noisy - action)  # the executed value, gradient to ã
    model_carry, out = variant.step(params, model_carry, StepInput(obs=obs, action=a_in, is_first=is_first))
    executed = jax.lax.stop_gradient(noisy)
    nxt, env_state2, reward, term, trunc, _ = jax.vmap(game.step, in_axes=(0, 0, 0, None))(
        jax.random.split(k_env, obs.shape[0]), env_state, executed, env_params)
    nxt = jax.lax.stop_gradient(resize_obs(nxt, size))
    reward = jax.lax.stop_gradient(reward.astype(jnp.float32))
    done = term | trunc
    fresh_obs, fresh_state = _reset_games(game, env_params, k_reset, obs.shape[0], size)
    env_state = jax.tree.map(
        lambda f, s: jnp.where(done.reshape(done.shape + (1,) * (s.ndim - 1)), f, s), fresh_state, env_state2)
    ep_ret, ep_len = ep_ret + reward, ep_len + 1
    stats = {"reward": reward, "done": done, "finished_return": jnp.where(done, ep_ret, 0.0),
             "finished_length": jnp.where(done, ep_len, 0), "action": executed}
    outs = {"logits": out["logits"], "obs": obs, "target": nxt,
            "pred_reward": out.get("reward", jnp.zeros_like(reward))}
    c = (model_carry, env_state, jnp.where(done[:, None, None], fresh_obs, nxt),
         jnp.where(done[:, None], 0.0, out["action"]), done, key,
         jnp.where(done, 0.0, ep_ret), jnp.where(done, 0, ep_len))
    return c, (outs, stats)


def rollout_carry(state: OnlineState):
    return (jax.lax.stop_gradient(state.train.carry), state.env_state, state.obs, state.action, state.is_first,
            state.key, state.episode_return, state.episode_length)


def chunk_objective(variant: Variant, outs, stats, hp: OnlineHParams):
    """(model loss, mean predicted reward, loss terms) of a chunk's outputs `[T, B, ...]`.
    Besides the weighted terms, `copy_bce` and `target_entropy` (weight 0) score copying the
    last frame and the floor on the same frames, for the excess ratio of the predictions."""
    target = jax.lax.stop_gradient(outs["target"])
    terms = {"obs_bce": bce_with_logits(outs["logits"], target),
             "copy_bce": jnp.mean(copy_last_bce(jax.lax.stop_gradient(outs["obs"]), target)),
             "target_entropy": jnp.mean(target_entropy(target))}
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
    model_carry, env_state, obs, action, is_first, key, ep_ret, ep_len = c
    new_state = state.replace(train=state.train.replace(carry=model_carry), env_state=env_state, obs=obs,
                              action=jax.lax.stop_gradient(action), is_first=is_first, key=key,
                              episode_return=ep_ret, episode_length=ep_len)
    return (model_loss, pred_reward), (new_state, terms, stats, noise_std)


def _ascent_scope(variant: Variant, tree, ascent_all):
    """The ascent gradient restricted to the controller D_a, or everywhere when `ascent_all`."""
    return {k: (v if k in variant.controller_groups else jax.tree.map(lambda x: ascent_all * x, v))
            for k, v in tree.items()}


def online_step_fn(variant: Variant, game, cfg: OnlineConfig, state: OnlineState, hp: OnlineHParams, env_params):
    """One chunk of acting, predicting and learning; see the module docstring."""
    params = state.train.params
    (model_loss, pred_reward), vjp, (new_state, terms, stats, noise_std) = jax.vjp(
        lambda p: _rollout(variant, game, cfg, p, state, hp, env_params), params, has_aux=True)
    active = (state.train.step.astype(jnp.float32) >= hp.warmup_steps).astype(jnp.float32)
    lam = hp.ascent * active
    (g_model,) = vjp((jnp.ones(()), jnp.zeros(())))
    (g_reward,) = vjp((jnp.zeros(()), jnp.ones(())))
    grads = jax.tree.map(lambda m, r: m - lam * r, g_model, _ascent_scope(variant, g_reward, hp.ascent_all))
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
