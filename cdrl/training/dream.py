"""Online training with a replay buffer and a controller trained in imagination, as one program.

`cdrl.training.online` is the thesis's online learner: each chunk the model acts, and one
update learns from that chunk, the gradient of the predicted reward reaching the controller
through the real chunk's BPTT. This module separates the two learners, as world-model agents
do (Dreamer's train ratio and imagination), keeping the thesis's model and heads:

1. act: B games play T steps; the model sees o_t and the executed a_t and outputs ã_{t+1}
   (the controller D_a on the core's output). The buttons executed next are drawn from
   Bernoulli(p) with p = (1 - ε) ã + ε / 2 (ε: the exploration, decaying per update); the
   chunk (frames, executed buttons, rewards, episode starts, the model's carry at its start)
   is written into a ring buffer of the last `replay` chunks;
2. learn, `model_updates` times: draw a chunk from the buffer;
   - model: one update on it, as offline training makes it (`cdrl.training.step.chunk_loss`:
     teacher-forced on the executed buttons, from the carry stored with the chunk, behind the
     divergence guard), with the model's own optimiser (SGD with momentum, the offline
     recipes' numbers);
   - controller: from every real state of that chunk (the model's carries along it) the
     model imagines `horizon` steps fed its own predictions and the controller's
     actions (for closed loop − the error input is then zero: `FinalProposal.imagine_step`),
     and the controller (the FC layer's action-code columns and D_a, `controller_mask`) is
     updated with its own optimiser (Adam) on one of three objectives:
     - `imagine`: gradient ascent on the discounted predicted reward of the imagined steps,
       the action ã fed in as it is (deterministic, differentiated through the model);
     - `critic`: an actor-critic in imagination (DreamerV3's recipe for discrete actions):
       buttons drawn from Bernoulli(ã), a critic V(h) on the core's output trained on the
       imagined λ-returns, the actor by REINFORCE with the returns normalised by their 5-95 %
       range (at least 1) and an entropy bonus;
     - `value`: the buttons' values one model step ahead, learnt from real returns
       (`_value_objective`).
   The controller's objective is off for `warmup_steps` updates, while the model learns alone
   (the critic learns from the start).

`real` learns the controller without imagination: once per chunk, before the model's updates,
an actor-critic on the model's states along the chunk just played, from its real rewards
(`_real_update`; with scope `all` its gradient shapes the core too).

In imagination the model never sees a gradient of the controller's objective, so it cannot
"predict more reward" to please the controller (what scope `all` of the thesis's ascent does).
"""
from __future__ import annotations

import dataclasses
import itertools
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from cdrl.data.frames import pixel_bce
from cdrl.data.stream import Chunk
from cdrl.models import nets
from cdrl.models.base import StepInput, Variant
from cdrl.training.online import Games, copy_scores, reset_games, step_games
from cdrl.training.optim import HParams, OptHParams, init_opt_state
from cdrl.training.ppo import clipped_surrogate
from cdrl.training.step import TrainState, chunk_loss, guarded_update, run_once, step_inputs

CONTROLLERS = ("imagine", "critic", "value", "real")
# Every combination of the three buttons (right, left, accelerate), pressed 1.0 or released 0.0.
BUTTON_COMBOS = np.asarray(list(itertools.product((0.0, 1.0), repeat=3)), np.float32)
CRITIC_HIDDEN = 128


@dataclasses.dataclass(frozen=True)
class DreamConfig:
    """Static shape: B games x T steps per chunk, `replay` chunks kept, `model_updates` per
    chunk, `horizon` imagined steps, the controller's objective (one of `CONTROLLERS`)."""

    num_envs: int = 8
    unroll: int = 16
    replay: int = 64
    model_updates: int = 4
    horizon: int = 15
    controller: str = "imagine"
    epochs: int = 4  # `real`: passes of the clipped update over each chunk played
    scope: str = "controller"  # `real`: what its gradient changes: the controller, or `all` (the core too)

    def __post_init__(self):
        for name in ("num_envs", "unroll", "replay", "model_updates", "horizon", "epochs"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.controller not in CONTROLLERS:
            raise ValueError(f"unknown controller objective {self.controller!r}; choose one of {CONTROLLERS}")
        if self.scope not in ("controller", "all"):
            raise ValueError(f"scope must be controller or all, got {self.scope!r}")
        if self.scope == "all" and self.controller != "real":
            raise ValueError(f"scope all is for the real controller: {self.controller!r} learns in the model's "
                             "imagination, which must not bend to please it")


@flax.struct.dataclass
class DreamHParams:
    """Traced numbers (a `vmap` sweep can vary any of them)."""

    model: HParams  # the model's optimiser, loss weights and divergence threshold
    ctrl_opt: OptHParams  # the heads' optimiser: the controller's, the critic's and the reward head's
    ascent: jax.Array  # weight of the controller's objective (0: the model learns alone)
    explore: jax.Array  # ε at update 0: the chance a button is drawn uniformly
    explore_decay: jax.Array  # per update: ε_k = explore * explore_decay ** k
    warmup_steps: jax.Array  # updates before the controller's objective is on
    gamma: jax.Array  # discount of imagined rewards
    lam: jax.Array  # λ of the critic's λ-returns
    entropy: jax.Array  # the actor's entropy bonus (critic, value, real)
    clip_eps: jax.Array  # `real`: clip range of the probability ratio

    @classmethod
    def create(cls, model: HParams, ctrl_opt: OptHParams | None = None, ascent=1.0, explore=0.3,
               explore_decay=0.999, warmup_steps=100, gamma=0.95, lam=0.95, entropy=3e-3,
               clip_eps=0.2) -> "DreamHParams":
        f32 = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
        ctrl_opt = ctrl_opt if ctrl_opt is not None else OptHParams.create("adam", lr=3e-4, grad_clip=100.0)
        return cls(model, ctrl_opt, f32(ascent), f32(explore), f32(explore_decay), f32(warmup_steps), f32(gamma),
                   f32(lam), f32(entropy), f32(clip_eps))


@flax.struct.dataclass
class Replay:
    """A ring buffer of chunks: frames uint8 `[N, T + 1, B, S, S]` (o_0 .. o_T), executed
    buttons `[N, T, B, A]`, rewards `[N, T, B]` (r_{t+1}), episode starts `[N, T, B]`, the
    model's carry at each chunk's start (leading axis N), and how many are filled."""

    obs: jax.Array
    action: jax.Array
    reward: jax.Array
    is_first: jax.Array
    carry: Any
    filled: jax.Array
    cursor: jax.Array

    def chunk(self, i) -> tuple[Chunk, Any]:
        return Chunk(obs=self.obs[i, :-1], next_obs=self.obs[i, 1:], action=self.action[i], reward=self.reward[i],
                     is_first=self.is_first[i]), jax.tree.map(lambda x: x[i], self.carry)


@flax.struct.dataclass
class DreamState:
    model: TrainState  # the world model: params (controller included), its optimiser, acting carry, updates
    ctrl_opt_state: Any  # the controller's optimiser state
    reward_opt_state: Any  # the reward head's optimiser state (the heads' optimiser)
    critic: Any  # the critic's parameters (unused by `imagine`)
    critic_opt_state: Any
    replay: Replay
    games: Games
    action: jax.Array  # [B, A]: the buttons executed next
    key: jax.Array


def init_dream(variant: Variant, game, env_params, cfg: DreamConfig, key: jax.Array, hp: DreamHParams) -> DreamState:
    if not variant.has_controller:
        raise ValueError(f"variant {variant.name!r} has no controller; online training needs one of "
                         "action_loop, reward_prediction, final_proposal")
    return run_once(_init_dream, variant, game, env_params, cfg, key, hp, static_argnums=(0, 1, 3))


def _init_dream(variant, game, env_params, cfg, key, hp) -> DreamState:
    if not variant.predicts_reward:
        raise ValueError(f"variant {variant.name!r} predicts no reward: a controller trained in imagination needs "
                         "reward_prediction or final_proposal")
    k_params, k_critic, k_env, k_run = jax.random.split(key, 4)
    params = variant.init(k_params)
    b, s, t, n = cfg.num_envs, variant.arch.image_size, cfg.unroll, cfg.replay
    carry = variant.init_carry(b)
    critic = nets.init_mlp(k_critic, (variant.arch.lstm_size, CRITIC_HIDDEN, 1), final_selu=False)
    replay = Replay(obs=jnp.zeros((n, t + 1, b, s, s), jnp.uint8),
                    action=jnp.zeros((n, t, b, variant.arch.action_dim), jnp.float32),
                    reward=jnp.zeros((n, t, b), jnp.float32), is_first=jnp.zeros((n, t, b), bool),
                    carry=jax.tree.map(lambda x: jnp.zeros((n,) + x.shape, x.dtype), carry),
                    filled=jnp.zeros((), jnp.int32), cursor=jnp.zeros((), jnp.int32))
    model = TrainState(params=params, opt_state=init_opt_state(hp.model.opt, params), carry=carry,
                       step=jnp.zeros((), jnp.int32))
    return DreamState(model=model, ctrl_opt_state=init_opt_state(hp.ctrl_opt, params),
                      reward_opt_state=init_opt_state(hp.ctrl_opt, params), critic=critic,
                      critic_opt_state=init_opt_state(hp.ctrl_opt, critic), replay=replay,
                      games=reset_games(game, env_params, k_env, b, variant.arch),
                      action=jnp.zeros((b, variant.arch.action_dim)), key=k_run)


def draw_buttons(key, probs: jax.Array) -> jax.Array:
    """Buttons pressed (1.0) with probability `probs`, else released (0.0)."""
    return (jax.random.uniform(key, probs.shape) < probs).astype(jnp.float32)


def _act(variant: Variant, game, cfg: DreamConfig, state: DreamState, env_params, explore):
    """T steps of acting (no gradient). Returns (state, the chunk's frames, executed buttons,
    rewards and episode starts `[T, B, ...]`, game statistics)."""
    params = state.model.params

    def body(c, _):
        carry, games, action, key = c
        key, k_buttons, k_game = jax.random.split(key, 3)
        obs, is_first = games.obs, games.is_first
        carry, out = variant.step(params, carry, StepInput(obs=obs, action=action, is_first=is_first))
        games, nxt, reward, stats = step_games(game, env_params, games, action, k_game, variant.arch)
        probs = (1.0 - explore) * out["action"] + explore * 0.5
        next_action = jnp.where(games.is_first[:, None], 0.0, draw_buttons(k_buttons, probs))
        record = {"obs": obs, "next_obs": nxt, "action": action, "reward": reward, "is_first": is_first,
                  "h": variant.features(carry)}
        scores = {"pred_reward": out["reward"], "obs_bce": pixel_bce(out["logits"], nxt)}
        return (carry, games, next_action, key), (record, {**stats, **scores})

    (carry, games, action, key), (chunk, stats) = jax.lax.scan(
        body, (state.model.carry, state.games, state.action, state.key), None, length=cfg.unroll)
    state = state.replace(model=state.model.replace(carry=carry), games=games, action=action, key=key)
    return state, chunk, stats


def _store(replay: Replay, chunk: dict, carry0) -> Replay:
    """Write a chunk (and the model's carry at its start) over the oldest one."""
    frames = jnp.concatenate([chunk["obs"], chunk["next_obs"][-1:]], axis=0)
    i = replay.cursor
    put = lambda buf, x: buf.at[i].set(x.astype(buf.dtype))  # noqa: E731
    return replay.replace(obs=put(replay.obs, jnp.round(frames * 255.0)), action=put(replay.action, chunk["action"]),
                          reward=put(replay.reward, chunk["reward"]), is_first=put(replay.is_first, chunk["is_first"]),
                          carry=jax.tree.map(put, replay.carry, carry0),
                          filled=jnp.minimum(replay.filled + 1, replay.obs.shape[0]),
                          cursor=(replay.cursor + 1) % replay.obs.shape[0])


def _model_update(variant: Variant, state: DreamState, hp: DreamHParams, chunk: Chunk, carry) -> DreamState:
    """One guarded update of the model on `chunk` from `carry`, as offline training makes it;
    the controller's parameters get no gradient (they are the controller's to learn). The
    reward head's own parameters (`reward_mask`) step with the heads' optimiser (Adam), the
    rest with the model's (SGD): at the rates that train the frame predictor the reward head's
    squared error grows without bound, and at a weight small enough to hold it the head learns
    only the mean reward."""
    model = state.model
    (loss, (_, terms, _)), grads = jax.value_and_grad(
        lambda p: chunk_loss(variant, p, carry, hp.model, chunk), has_aux=True)(model.params)
    grads = jax.tree.map(lambda g, m: g * (1.0 - m), grads, variant.controller_mask(model.params))
    params, opt_state, guard = guarded_update(hp.model.opt, hp.model.diverge_threshold, model.params,
                                              model.opt_state, grads, loss)
    head, head_state, head_guard = guarded_update(hp.ctrl_opt, hp.model.diverge_threshold, model.params,
                                                  state.reward_opt_state, grads, loss)
    params = jax.tree.map(lambda s, a, m: jnp.where(m > 0, a, s), params, head, variant.reward_mask(model.params))
    guard = {**guard, "finite": guard["finite"] & head_guard["finite"],
             "diverged": guard["diverged"] | head_guard["diverged"]}
    model = model.replace(params=params, opt_state=opt_state)
    return state.replace(model=model, reward_opt_state=head_state), {"loss": loss, "terms": terms, **guard}


def _starts(variant: Variant, params, chunk: Chunk, carry):
    """The real states imagination starts from, flattened to `[T * B, ...]`: the model's carry
    after every step of `chunk`, its action output there (the buttons it would press next)
    and its predicted next frame (what it is fed first)."""

    def body(c, x):
        c, out = variant.step(params, c, x)
        return c, (c, out["action"], jax.nn.sigmoid(out["logits"]))

    _, (carries, actions, frames) = jax.lax.scan(body, carry, step_inputs(chunk))
    flat = lambda x: x.reshape((-1,) + x.shape[2:])  # noqa: E731
    return jax.tree.map(flat, carries), flat(actions), flat(frames)


def imagine(variant: Variant, cfg: DreamConfig, params, carry, action, frame, key, sample: bool):
    """`horizon` steps of the model fed its own predictions from `carry`, taking the pending
    `action`. With `sample` the buttons executed are drawn from Bernoulli(ã) (their
    probability and draw are returned); without, ã itself is fed in. Returns per step `[H, N]`:
    rewards r̃, features h, the action probabilities and the executed buttons."""

    def body(c, k):
        carry, action, frame = c
        executed = draw_buttons(k, action) if sample else action
        carry, out = variant.imagine_step(params, carry, frame, executed)
        frame = jax.nn.sigmoid(out["logits"]) if "logits" in out else frame
        return (carry, out["action"], frame), {"reward": out["reward"], "h": variant.features(carry),
                                               "probs": action, "buttons": executed}

    _, traj = jax.lax.scan(body, (carry, action, frame), jax.random.split(key, cfg.horizon))
    return traj


def lambda_returns(rewards, values, last, gamma, lam, not_done=None):
    """R_k = r_k + γ d_k ((1 - λ) V_{k+1} + λ R_{k+1}), R_H = `last`: λ-returns of `[H, N]`
    rewards with the values V_1 .. V_H after each step; `not_done` d_k (default 1) is 0 where the
    episode ended with r_k, which then bootstraps nothing."""
    not_done = jnp.ones_like(rewards) if not_done is None else jnp.broadcast_to(not_done, rewards.shape)

    def body(nxt, x):
        r, v_next, nd = x
        ret = r + gamma * nd * ((1.0 - lam) * v_next + lam * nxt)
        return ret, ret

    _, rets = jax.lax.scan(body, last, (rewards, values, not_done), reverse=True)
    return rets


def critic_value(critic, h):
    return nets.mlp(critic, h, final_selu=False)[..., 0]


def _controller_objective(variant, cfg, hp, params, critic, starts, key):
    """The controller's loss (to minimise) and the critic's, with their terms."""
    carry, action, frame = starts
    sample = cfg.controller == "critic"
    traj = imagine(variant, cfg, params, carry, action, frame, key, sample)
    discount = hp.gamma ** jnp.arange(cfg.horizon, dtype=jnp.float32)[:, None]
    if not sample:
        objective = jnp.mean(jnp.sum(discount * traj["reward"], axis=0))
        return -objective, (jnp.zeros(()), {"imagined_return": objective})
    values = critic_value(critic, jax.lax.stop_gradient(traj["h"]))  # V after each imagined step
    rewards = jax.lax.stop_gradient(traj["reward"])
    rets = jax.lax.stop_gradient(lambda_returns(rewards, values, values[-1], hp.gamma, hp.lam))
    h0 = jax.lax.stop_gradient(variant.features(carry))
    base = critic_value(critic, h0)  # V of the state each step's buttons were drawn in
    before = jnp.concatenate([base[None], values[:-1]], axis=0)
    critic_loss = 0.5 * jnp.mean(jnp.square(before - rets))
    scale = jnp.maximum(1.0, jnp.percentile(rets, 95) - jnp.percentile(rets, 5))
    adv = jax.lax.stop_gradient((rets - before) / scale)
    logp = button_log_prob(traj["probs"], traj["buttons"])
    ent = button_entropy(traj["probs"])
    actor_loss = -jnp.mean(logp * adv) - hp.entropy * jnp.mean(ent)
    return actor_loss, (critic_loss, {"imagined_return": jnp.mean(rets[0]), "critic_loss": critic_loss,
                                      "entropy": jnp.mean(ent)})


def after_one_step(variant: Variant, params, carry, frame, buttons):
    """The model's state after one imagined step from `carry` (`[N, ...]`, its prediction
    `frame`) taking `buttons` `[N, A]`: what pressing them next leads to, as the model sees it."""
    return variant.imagine_step(params, carry, frame, buttons)[0]


def button_log_probs(probs: jax.Array) -> jax.Array:
    """log P(combo) `[8, N]` of every button combination under independent Bernoulli(`probs` `[N, 3]`)."""
    p = jnp.clip(probs, 1e-6, 1 - 1e-6)
    c = BUTTON_COMBOS[:, None, :]
    return jnp.sum(c * jnp.log(p)[None] + (1.0 - c) * jnp.log1p(-p)[None], axis=-1)


def _value_objective(variant, hp, params, critic, chunk: Chunk, starts):
    """`value`: an action value read through the model's step, learnt from the real returns.

    The carry c_t has seen o_t and a_t; the controller's output there, ã_{t+1}, is the
    probability of each button at t + 1, before o_{t+1} is seen. Q(c_t, a) = W(h of the state
    after one imagined step from c_t taking a): the critic W reads the core after the model
    has taken the action, so the action's effect goes through the world model's own dynamics.
    W learns from the chunk's real rewards: for the executed a_{t+1}, the λ-return of the
    real r_{t+2}, r_{t+3}, ... bootstrapped with W of the same one-step states further along.
    The controller ascends the expected Q under its Bernoulli buttons, summed exactly over the
    8 combinations (no sampling), plus an entropy bonus; the Q values are behind a
    stop-gradient, so the gradient reaches the controller through its probabilities only."""
    carry, probs, frame = starts  # [T * B, ...], probs: ã_{t+1} with the gradient of the controller
    t, b = chunk.is_first.shape
    fixed = jax.lax.stop_gradient(params)
    # Q of every combination from every carry: [8, T * B]
    q_all = jax.vmap(lambda a: critic_value(critic, variant.features(
        after_one_step(variant, fixed, carry, frame, jnp.broadcast_to(a, probs.shape)))))(BUTTON_COMBOS)
    q_all = jax.lax.stop_gradient(q_all)
    expected = jnp.sum(jnp.exp(button_log_probs(probs)) * q_all, axis=0)
    ent = button_entropy(probs)
    # E[Q] + α H: the factorised policy closest (in KL) to softmax(Q / α) over the combinations;
    # α (`entropy`) is in the units of the return
    actor_loss = -jnp.mean(expected) - hp.entropy * jnp.mean(ent)
    # The critic on the executed buttons: W(q_k), q_k = one step from c_{k-1} taking a_k, k = 1 .. T - 1.
    grid = lambda x: x.reshape((t, b) + x.shape[1:])  # noqa: E731
    prev = jax.tree.map(lambda x: grid(x)[:-1].reshape((-1,) + x.shape[1:]), (carry, frame))
    executed = chunk.action[1:].reshape(-1, chunk.action.shape[-1])
    w = critic_value(critic, variant.features(after_one_step(variant, fixed, *prev, executed))).reshape(t - 1, b)
    # targets for k = 1 .. T - 2 (the last one bootstraps them): r_{k+1} + γ ..., no bootstrap
    # across an episode's end; q_k is not a state of the episode that o_k starts
    not_done = (~chunk.is_first[2:]).astype(jnp.float32)
    targets = lambda_returns(chunk.reward[1:-1], jax.lax.stop_gradient(w[1:]), jax.lax.stop_gradient(w[-1]),
                             hp.gamma, hp.lam, not_done)
    valid = (~chunk.is_first[1:-1]).astype(jnp.float32)
    critic_loss = 0.5 * jnp.sum(valid * jnp.square(w[:-1] - targets)) / jnp.maximum(jnp.sum(valid), 1.0)
    gap = jnp.max(q_all, axis=0) - jnp.min(q_all, axis=0)
    return actor_loss, (critic_loss, {"imagined_return": jnp.mean(expected), "critic_loss": critic_loss,
                                      "entropy": jnp.mean(ent), "q_gap": jnp.mean(gap)})


def _controller_update(variant, cfg, state: DreamState, hp: DreamHParams, starts, key, on, chunk: Chunk):
    params = state.model.params

    def losses(p, critic):
        if cfg.controller == "value":
            carry, _, frame = starts
            probs = variant.heads(p, variant.fc(p, variant.features(carry)))["action"]
            actor, (critic_loss, terms) = _value_objective(variant, hp, p, critic, chunk, (carry, probs, frame))
        else:
            actor, (critic_loss, terms) = _controller_objective(variant, cfg, hp, p, critic, starts, key)
        return hp.ascent * on * actor + critic_loss, (actor, terms)

    (total, (actor, terms)), (g_params, g_critic) = jax.value_and_grad(losses, argnums=(0, 1), has_aux=True)(
        params, state.critic)
    return _step_controller(variant, state, hp, g_params, g_critic, total), {"controller_loss": actor, **terms}


def _step_controller(variant, state: DreamState, hp: DreamHParams, g_params, g_critic, total,
                     everything: bool = False) -> DreamState:
    """One step of the controller's optimiser (on its parameters only, or with `everything`
    on all of the model's) and of the critic's."""
    params = state.model.params
    mask = jax.tree.map(jnp.ones_like, params) if everything else variant.controller_mask(params)
    g_params = jax.tree.map(lambda g, m: g * m, g_params, mask)
    new, opt_state, _ = guarded_update(hp.ctrl_opt, hp.model.diverge_threshold, params, state.ctrl_opt_state,
                                       g_params, total)
    new = jax.tree.map(lambda n, o, m: jnp.where(m > 0, n, o), new, params, mask)  # only the controller moves
    critic, critic_opt, _ = guarded_update(hp.ctrl_opt, hp.model.diverge_threshold, state.critic,
                                           state.critic_opt_state, g_critic, total)
    return state.replace(model=state.model.replace(params=new), ctrl_opt_state=opt_state, critic=critic,
                         critic_opt_state=critic_opt)


def button_entropy(probs: jax.Array) -> jax.Array:
    """The entropy of independent Bernoulli(`probs`) buttons, summed over the last axis."""
    p = jnp.clip(probs, 1e-6, 1 - 1e-6)
    return -jnp.sum(p * jnp.log(p) + (1 - p) * jnp.log1p(-p), axis=-1)


def button_log_prob(probs: jax.Array, buttons: jax.Array) -> jax.Array:
    """log P(`buttons`) under independent Bernoulli(`probs`), summed over the last axis."""
    p = jnp.clip(probs, 1e-6, 1 - 1e-6)
    return jnp.sum(buttons * jnp.log(p) + (1.0 - buttons) * jnp.log1p(-p), axis=-1)


def real_advantages(h_values, reward, is_first, first_after, gamma, lam):
    """The λ-returns and the mask of the decisions of a chunk played, for `real`.

    The controller's output at step t (from h_t, having seen o_t and a_t) is the probability
    of the buttons a_{t+1}, executed at t + 1 for the reward r_{t+2} (`reward[t + 1]`). So the
    decision of step t (t = 0 .. T - 2) is scored by R_t = r_{t+2} + γ ((1 - λ) V_{t+1} +
    λ R_{t+1}), R_{T-1} = V_{T-1}, with V_t = `h_values[t]`; no bootstrap across an episode's end
    (the episode that a_{t+1} plays in ends with r_{t+2} when o_{t+2} starts a new one:
    `is_first[t + 2]`, `first_after` for t + 2 = T). A decision counts only if a_{t+1} was drawn
    from it: not when o_{t+1} starts a new episode (its buttons are then released). Returns
    (R `[T - 1, B]`, valid `[T - 1, B]`)."""
    first = jnp.concatenate([is_first, first_after[None]], axis=0)  # o_0 .. o_T starts an episode
    not_done = (~first[2:]).astype(jnp.float32)
    rets = lambda_returns(reward[1:], h_values[1:], h_values[-1], gamma, lam, not_done)
    return rets, (~first[1:-1]).astype(jnp.float32)


def _real_update(variant, cfg: DreamConfig, state: DreamState, hp: DreamHParams, chunk: dict, carry0, explore, on):
    """`real`: the controller and the critic on the chunk just played, from its real rewards.

    The states are the model's own h_t along the chunk, teacher-forced on the executed buttons
    from `carry0` (the controller's parameters do not change them). The critic V(h_t) learns
    the λ-returns of the real rewards (`real_advantages`); the controller is updated by PPO's
    clipped surrogate on the probability it drew the executed buttons with, (1 - ε) ã + ε / 2,
    the advantages normalised over the chunk, plus an entropy bonus on ã; `epochs` passes over
    the chunk. With scope `controller` no gradient reaches the world model: it learns its frames
    only, and the controller reads what it has learnt (h as recorded while acting). With scope
    `all` the actor's and the critic's gradients reach the core and the encoder too, stepped
    by the controller's optimiser beside the model's own updates on its frames."""
    everything = cfg.scope == "all"
    recorded = Chunk(obs=chunk["obs"], next_obs=chunk["next_obs"], action=chunk["action"], reward=chunk["reward"],
                     is_first=chunk["is_first"])

    def features(params):
        if not everything:
            return jax.lax.stop_gradient(chunk["h"])  # [T, B, H]

        def body(c, x):
            c, _ = variant.step(params, c, x)
            return c, variant.features(c)

        return jax.lax.scan(body, carry0, step_inputs(recorded))[1]

    executed = jnp.concatenate([chunk["action"][1:], state.action[None]], axis=0)[:-1]  # a_{t+1}, t < T - 1

    def probs_of(params, h):
        a = variant.heads(params, variant.fc(params, h[:-1]))["action"]
        return (1.0 - explore) * a + explore * 0.5, a

    h0 = jax.lax.stop_gradient(chunk["h"])
    old_logp = jax.lax.stop_gradient(button_log_prob(probs_of(state.model.params, h0)[0], executed))
    rets, valid = real_advantages(critic_value(state.critic, h0), chunk["reward"], chunk["is_first"],
                                  state.games.is_first, hp.gamma, hp.lam)
    rets = jax.lax.stop_gradient(rets)
    count = jnp.maximum(jnp.sum(valid), 1.0)
    masked_mean = lambda x: jnp.sum(valid * x) / count  # noqa: E731

    def losses(params, critic):
        h = features(params)
        values = critic_value(critic, h[:-1])
        adv = jax.lax.stop_gradient(rets - values)
        mean = masked_mean(adv)
        adv = (adv - mean) / jnp.sqrt(masked_mean(jnp.square(adv - mean)) + 1e-8)
        probs, a = probs_of(params, h)
        ratio = jnp.exp(button_log_prob(probs, executed) - old_logp)
        ent = button_entropy(a)
        actor = -masked_mean(clipped_surrogate(ratio, adv, hp.clip_eps)) - hp.entropy * masked_mean(ent)
        critic_loss = 0.5 * masked_mean(jnp.square(values - rets))
        terms = {"imagined_return": masked_mean(rets), "critic_loss": critic_loss, "entropy": masked_mean(ent),
                 "clip_fraction": masked_mean((jnp.abs(ratio - 1.0) > hp.clip_eps).astype(jnp.float32))}
        return hp.ascent * on * actor + critic_loss, (actor, terms)

    def epoch(state, _):
        (total, (actor, terms)), (g_params, g_critic) = jax.value_and_grad(losses, argnums=(0, 1), has_aux=True)(
            state.model.params, state.critic)
        state = _step_controller(variant, state, hp, g_params, g_critic, total, everything)
        return state, {"controller_loss": actor, **terms}

    state, terms = jax.lax.scan(epoch, state, None, length=cfg.epochs)
    return state, jax.tree.map(lambda x: x[-1], terms)


def dream_step_fn(variant: Variant, game, cfg: DreamConfig, state: DreamState, hp: DreamHParams, env_params):
    """Act, store, update the model, update the controller: see the module docstring."""
    step = state.model.step.astype(jnp.float32)
    explore = hp.explore * hp.explore_decay ** step
    carry0 = state.model.carry
    key, k_model = jax.random.split(state.key)
    state, chunk, stats = _act(variant, game, cfg, state.replace(key=key), env_params, explore)
    state = state.replace(replay=_store(state.replay, chunk, jax.lax.stop_gradient(carry0)))
    scores = copy_scores(chunk["obs"], chunk["next_obs"])
    on = (step >= hp.warmup_steps).astype(jnp.float32)
    if cfg.controller == "real":  # on the chunk just played, before the model moves (on-policy)
        state, real_terms = _real_update(variant, cfg, state, hp, chunk, carry0, explore, on)

    def learn(state: DreamState, k):
        """One model update on a chunk drawn from the buffer, then (but for `real`) one
        controller update from that chunk's states."""
        k_draw, k_imagine = jax.random.split(k)
        replayed, carry = state.replay.chunk(jax.random.randint(k_draw, (), 0, state.replay.filled))
        state, model_m = _model_update(variant, state, hp, replayed, carry)
        if cfg.controller == "real":
            return state, (model_m, {})
        starts = _starts(variant, jax.lax.stop_gradient(state.model.params), replayed, carry)
        state, ctrl_terms = _controller_update(variant, cfg, state, hp, starts, k_imagine, on, replayed)
        return state, (model_m, ctrl_terms)

    state, (model_m, ctrl_m) = jax.lax.scan(learn, state, jax.random.split(k_model, cfg.model_updates))
    state = state.replace(model=state.model.replace(step=state.model.step + 1))
    last = jax.tree.map(lambda x: x[-1], model_m)
    ctrl_terms = real_terms if cfg.controller == "real" else jax.tree.map(jnp.mean, ctrl_m)
    metrics = {
        "loss": last["loss"],
        # The model's scores on the chunk it acted in, before learning from it (obs_bce beside
        # copy_bce and target_entropy: the excess ratio of its predictions); the training
        # terms of its last update (on a replayed chunk) as model_<term>.
        "terms": {**{f"model_{k}": v for k, v in last["terms"].items()}, **scores, **ctrl_terms,
                  "obs_bce": jnp.mean(stats["obs_bce"]), "pred_reward": jnp.mean(stats["pred_reward"])},
        "reward": jnp.mean(stats["reward"]),
        "episodes": jnp.sum(stats["done"]),
        "return_sum": jnp.sum(stats["finished_return"]),
        "length_sum": jnp.sum(stats["finished_length"]),
        "action_mean": jnp.mean(chunk["action"], axis=(0, 1)),
        "explore": explore,
        "controller_on": on,
        "ratios": last["ratios"],
        "max_ratio": jnp.max(model_m["max_ratio"]),
        "worst_group": last["worst_group"],
        "finite": jnp.all(model_m["finite"]),
        "diverged": jnp.any(model_m["diverged"]),
    }
    return state, metrics


dream_step = jax.jit(dream_step_fn, static_argnums=(0, 1, 2), donate_argnums=3)
