"""`ppo`: a model-free baseline, proximal policy optimisation against the built-in game.

One train step is a jitted function in the style of purejaxrl:

1. rollout: a `lax.scan` over T steps in which B games (`vmap`) are played by the current
   policy; every step records the frame, the sampled buttons, their log-probability, the
   value estimate, the reward and whether the episode ended. A finished game is reset at
   once (`cdrl.learners.game_batch`), and its return and length are counted;
2. advantages: the value of the last frame bootstraps generalised advantage estimation
   (GAE, a reverse `lax.scan`); the value targets are the advantages plus the values;
3. learning: `epochs` passes over the T * B samples, each in a fresh random order cut into
   `minibatches`, one optimiser update per minibatch (nested `lax.scan`s), each behind the
   project's divergence guard (`cdrl.training.step.guarded_update`).

The network sees the frames the model-based controller sees: the game's frames resized to
`arch.image_size`, through the project's observation encoder E_o (`nets.obs_encoder`), then a
SELU torso of `hidden` units and two linear heads: the logits of three independent Bernoulli
buttons (right, left, accelerate; a pressed button is executed as 1.0, a released one as 0.0)
and a scalar value. The policy has no memory: one frame in, one action out.

Conventions follow "The 37 implementation details of PPO" (Huang et al. 2022) and purejaxrl:
Adam (lr 2.5e-4) with global gradient-norm clipping at 0.5; gamma 0.99, lambda 0.95;
the clipped surrogate with clip 0.2; the value loss clipped with the same 0.2 around the
rollout's values, weighted 0.5 and halved; entropy bonus 0.01; advantages normalised per
minibatch (population std, plus 1e-8); the policy head initialised 100 times smaller than
the project's Glorot initialisation (near-uniform buttons at the start), the value head at scale 1.
Two choices differ from those sources: Adam's epsilon is optax's 1e-8 (theirs 1e-5; the
project's optimisers have no such field), and the network is the project's (SELU, LeCun/Glorot,
not tanh/ReLU with orthogonal initialisation), so that PPO and the model-based controller share
the encoder architecture.

Truncation: an episode cut at the game's step cap is treated like a termination, not
bootstrapped from the value of the cut-off state (as purejaxrl does with gymnax's single done
flag). The policy does not see the step count, so the value targets of the last steps before
the cap are biased low; with a cap much longer than the horizon 1 / (1 - gamma) few samples are.

Every number of `PPOHParams` is a traced array, so one compiled program serves any values
(and a `vmap` over a stack of them); the shapes are `PPOConfig`'s and `ArchConfig`'s.
"""
from __future__ import annotations

import dataclasses
import functools
import numbers
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp

from cdrl.data.frames import model_obs
from cdrl.models import nets
from cdrl.models.arch import ArchConfig
from cdrl.options import AGENT_RECIPE, CONTROL, OptimOptions
from cdrl.learners.api import Learner
from cdrl.learners.game_batch import Games, Observation, observe, reset_games, step_games
from cdrl.training.optim import OptHParams, init_opt_state
from cdrl.training.step import guarded_update, run_once

NUM_BUTTONS = 3  # right, left, accelerate
POLICY_INIT_SCALE = 0.01
VALUE_INIT_SCALE = 1.0


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """Static shape of PPO: B games, T steps per update, `epochs` x `minibatches` optimiser
    updates per rollout, `hidden` units in the torso."""

    num_envs: int = AGENT_RECIPE["batch"]
    unroll: int = AGENT_RECIPE["unroll"]
    epochs: int = CONTROL.ppo_epochs
    minibatches: int = CONTROL.ppo_minibatches
    hidden: int = 256

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not isinstance(v, numbers.Integral) or isinstance(v, bool) or v < 1:
                raise ValueError(f"{f.name} must be an integer >= 1, got {v!r}")
        if self.samples % self.minibatches:
            raise ValueError(f"num_envs * unroll ({self.num_envs} * {self.unroll} = {self.samples}) must divide "
                             f"by minibatches ({self.minibatches})")

    @property
    def samples(self) -> int:
        """Samples per rollout: T * B."""
        return self.num_envs * self.unroll

    @property
    def minibatch_size(self) -> int:
        return self.samples // self.minibatches


@flax.struct.dataclass
class PPOHParams:
    """Traced numbers of PPO (a `vmap` sweep can vary any of them)."""

    opt: OptHParams  # the optimiser (Adam, lr 2.5e-4, gradient clip 0.5 by default)
    gamma: jax.Array  # discount
    gae_lambda: jax.Array
    clip_eps: jax.Array  # the ratio's clip range, and the value clip
    value_coef: jax.Array
    entropy_coef: jax.Array
    diverge_threshold: jax.Array

    @classmethod
    def create(cls, lr=AGENT_RECIPE["lr"], gamma=CONTROL.gamma, gae_lambda=CONTROL.gae_lambda,
               clip_eps=CONTROL.clip_eps, value_coef=CONTROL.value_coef, entropy_coef=CONTROL.entropy_coef,
               diverge_threshold=OptimOptions.diverge_threshold, grad_clip=AGENT_RECIPE["grad_clip"],
               opt: OptHParams | None = None) -> "PPOHParams":
        """The defaults are a run's (`cdrl.options`). `opt`: the optimiser's numbers (default:
        Adam with `lr`, betas 0.9 / 0.999 and global gradient-norm clipping at `grad_clip`,
        which it replaces)."""
        positive, non_negative, unit = (0.0, False, None), (0.0, True, None), (0.0, True, 1.0)
        for name, v, (lo, lo_ok, hi) in [
                ("lr", lr, positive), ("gamma", gamma, unit), ("gae_lambda", gae_lambda, unit),
                ("clip_eps", clip_eps, positive), ("value_coef", value_coef, non_negative),
                ("entropy_coef", entropy_coef, non_negative), ("diverge_threshold", diverge_threshold, positive),
                ("grad_clip", grad_clip, non_negative)]:
            # Python numbers only: arrays (a sweep's stack, a traced value) are the caller's to check.
            if not isinstance(v, (int, float)):
                continue
            if not (v > lo or (lo_ok and v == lo)) or (hi is not None and v > hi):
                rng = f"{'[' if lo_ok else '('}{lo}, {hi if hi is not None else 'inf'}{']' if hi is not None else ')'}"
                raise ValueError(f"{name} must lie in {rng}, got {v!r}")
        f32 = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
        opt = opt if opt is not None else OptHParams.create(name="adam", lr=lr, momentum=0.9, b2=0.999,
                                                            grad_clip=grad_clip)
        return cls(opt, f32(gamma), f32(gae_lambda), f32(clip_eps), f32(value_coef), f32(entropy_coef),
                   f32(diverge_threshold))


@flax.struct.dataclass
class PPOState:
    params: Any
    opt_state: Any
    games: Games  # the B games: states, the frames the policy sees next, episode counters
    key: jax.Array
    step: jax.Array  # int32: updates (rollouts) done


# --------------------------------------------------------------------------- the network


def init_params(arch: ArchConfig, key: jax.Array, hidden: int = 256):
    """E_o, a SELU torso of `hidden` units, the policy head (kernel x 0.01) and the value head."""
    k_enc, k_torso, k_pi, k_v = jax.random.split(key, 4)
    policy = nets.init_mlp(k_pi, (hidden, NUM_BUTTONS), final_selu=False)["dense0"]
    value = nets.init_mlp(k_v, (hidden, 1), final_selu=False)["dense0"]
    return {
        "obs_enc": nets.init_obs_encoder(k_enc, arch),
        "torso": nets.init_mlp(k_torso, (arch.obs_code, hidden), final_selu=True),
        "policy": {**policy, "kernel": POLICY_INIT_SCALE * policy["kernel"]},
        "value": {**value, "kernel": VALUE_INIT_SCALE * value["kernel"]},
    }


def policy_value(arch: ArchConfig, params, obs: jax.Array):
    """Frames `[..., S, S]` at `arch.image_size` -> (button logits `[..., 3]`, value `[...]`)."""
    lead = obs.shape[:-2]
    code = nets.obs_encoder(params["obs_enc"], arch, obs.reshape((-1,) + obs.shape[-2:]))
    h = nets.mlp(params["torso"], code, final_selu=True)
    logits = nets.dense(params["policy"], h)
    value = nets.dense(params["value"], h)[..., 0]
    return logits.reshape(lead + (NUM_BUTTONS,)), value.reshape(lead)


def log_prob(logits: jax.Array, action: jax.Array) -> jax.Array:
    """log pi(a | s) of 0/1 buttons `action` under independent Bernoullis: summed over the buttons."""
    return jnp.sum(action * jax.nn.log_sigmoid(logits) + (1.0 - action) * jax.nn.log_sigmoid(-logits), axis=-1)


def entropy(logits: jax.Array) -> jax.Array:
    """Sum of the buttons' Bernoulli entropies: p softplus(-l) + (1 - p) softplus(l) each."""
    p = jax.nn.sigmoid(logits)
    return jnp.sum(p * jax.nn.softplus(-logits) + (1.0 - p) * jax.nn.softplus(logits), axis=-1)


def sample_action(key: jax.Array, logits: jax.Array) -> jax.Array:
    """Each button pressed (1.0) with probability sigmoid(logit), else 0.0."""
    return jax.random.bernoulli(key, jax.nn.sigmoid(logits)).astype(jnp.float32)


# --------------------------------------------------------------------------- games and rollout


def _init_ppo(arch, game, env_params, cfg, key, hp) -> PPOState:
    k_params, k_env, k_run = jax.random.split(key, 3)
    params = init_params(arch, k_params, cfg.hidden)
    return PPOState(params=params, opt_state=init_opt_state(hp.opt, params),
                    games=reset_games(game, env_params, k_env, cfg.num_envs, arch), key=k_run,
                    step=jnp.zeros((), jnp.int32))


def gae(rewards, values, dones, last_value, gamma, gae_lambda):
    """Generalised advantage estimates `[T, ...]` (a reverse `lax.scan`):
    delta_t = r_t + gamma V(s_{t+1}) (1 - done_t) - V(s_t);
    A_t = delta_t + gamma lambda (1 - done_t) A_{t+1}, with V(s_T) = `last_value`.
    `done_t` (terminated or truncated) ends the sum: a truncated episode is not bootstrapped."""
    not_done = 1.0 - dones.astype(jnp.float32)
    next_values = jnp.concatenate([values[1:], last_value[None]], axis=0)

    def back(a_next, x):
        r, v, v_next, nd = x
        delta = r + gamma * v_next * nd - v
        a = delta + gamma * gae_lambda * nd * a_next
        return a, a

    _, adv = jax.lax.scan(back, jnp.zeros_like(last_value), (rewards, values, next_values, not_done), reverse=True)
    return adv


# --------------------------------------------------------------------------- the loss and the updates


def clipped_surrogate(ratio, advantages, clip_eps):
    """PPO's clipped surrogate per sample, min(ρ A, clip(ρ, 1 - ε, 1 + ε) A), to be maximised."""
    return jnp.minimum(ratio * advantages, jnp.clip(ratio, 1.0 - clip_eps, 1.0 + clip_eps) * advantages)


def clipped_loss(new_log_prob, old_log_prob, advantages, new_value, old_value, returns, ent, hp: PPOHParams):
    """PPO's loss of one minibatch from its per-sample numbers. The advantages are normalised here
    (mean 0, std 1 over the minibatch). Returns (loss, terms)."""
    adv = (advantages - jnp.mean(advantages)) / (jnp.std(advantages) + 1e-8)
    log_ratio = new_log_prob - old_log_prob
    ratio = jnp.exp(log_ratio)
    policy_loss = -jnp.mean(clipped_surrogate(ratio, adv, hp.clip_eps))
    v_clipped = old_value + jnp.clip(new_value - old_value, -hp.clip_eps, hp.clip_eps)
    value_loss = 0.5 * jnp.mean(jnp.maximum(jnp.square(new_value - returns), jnp.square(v_clipped - returns)))
    mean_entropy = jnp.mean(ent)
    loss = policy_loss + hp.value_coef * value_loss - hp.entropy_coef * mean_entropy
    terms = {"policy_loss": policy_loss, "value_loss": value_loss, "entropy": mean_entropy,
             "approx_kl": jnp.mean((ratio - 1.0) - log_ratio),  # the k3 estimator of KL(old || new)
             "clip_frac": jnp.mean((jnp.abs(ratio - 1.0) > hp.clip_eps).astype(jnp.float32))}
    return loss, terms


def minibatch_loss(arch: ArchConfig, params, mb, hp: PPOHParams):
    """`clipped_loss` of the network on a minibatch `mb` (dict of obs, action, log_prob, value,
    advantage, return; each `[N, ...]`)."""
    logits, value = policy_value(arch, params, mb["obs"])
    return clipped_loss(log_prob(logits, mb["action"]), mb["log_prob"], mb["advantage"], value, mb["value"],
                        mb["return"], entropy(logits), hp)


def update(arch: ArchConfig, cfg: PPOConfig, params, opt_state, batch, hp: PPOHParams, key: jax.Array):
    """`epochs` x `minibatches` guarded optimiser updates on `batch` (dict of `[T * B, ...]`
    arrays), each epoch in a fresh random order. Returns (params, opt_state, per-update metrics
    stacked `[epochs, minibatches, ...]`)."""
    grad_fn = jax.value_and_grad(lambda p, mb: minibatch_loss(arch, p, mb, hp), has_aux=True)

    def one_update(c, mb):
        params, opt_state = c
        (loss, terms), grads = grad_fn(params, mb)
        params, opt_state, guard = guarded_update(hp.opt, hp.diverge_threshold, params, opt_state, grads, loss)
        return (params, opt_state), {"loss": loss, "terms": terms, **guard}

    def one_epoch(c, k):
        order = jax.random.permutation(k, cfg.samples)
        mbs = jax.tree.map(lambda x: x[order].reshape((cfg.minibatches, cfg.minibatch_size) + x.shape[1:]), batch)
        return jax.lax.scan(one_update, c, mbs)

    (params, opt_state), per_update = jax.lax.scan(one_epoch, (params, opt_state), jax.random.split(key, cfg.epochs))
    return params, opt_state, per_update


def reduce_updates(per_update):
    """The per-update metrics `[epochs, minibatches, ...]` as one set: loss and terms averaged; the
    guard's ratios of the last update, max_ratio (and its worst_group) over all, finite if all
    were, diverged if any was."""
    flat = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), per_update)
    worst = jnp.argmax(flat["max_ratio"])
    return {"loss": jnp.mean(flat["loss"]), "terms": jax.tree.map(jnp.mean, flat["terms"]),
            "ratios": flat["ratios"][-1], "max_ratio": flat["max_ratio"][worst],
            "worst_group": flat["worst_group"][worst], "finite": jnp.all(flat["finite"]),
            "diverged": jnp.any(flat["diverged"])}


def flatten_rollout(traj, advantages):
    """The rollout's records `[T, B, ...]` and advantages as the update's `[T * B, ...]` samples."""
    batch = {"obs": traj["obs"], "action": traj["action"], "log_prob": traj["log_prob"], "value": traj["value"],
             "advantage": advantages, "return": advantages + traj["value"]}
    return jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), batch)


class PPO(Learner):
    """PPO; see the module docstring. `model` is the `ArchConfig` of the policy's encoder."""

    name = "ppo"
    row = "ppo"
    has_world_model = False

    @classmethod
    def from_run(cls, cfg, model, game, env_params) -> "PPO":
        config = PPOConfig(num_envs=cfg.batch, unroll=cfg.unroll, epochs=cfg.ppo_epochs, minibatches=cfg.ppo_minibatches)
        hp = PPOHParams.create(opt=cfg.opt_hparams(), gamma=cfg.gamma, gae_lambda=cfg.gae_lambda,
                               clip_eps=cfg.clip_eps, value_coef=cfg.value_coef, entropy_coef=cfg.entropy_coef,
                               diverge_threshold=cfg.diverge_threshold)
        return cls(model, game, config, hp, env_params)

    def init(self, key: jax.Array) -> PPOState:
        """Fresh parameters, optimiser state and B new games."""
        return run_once(_init_ppo, self.model, self.game, self.env_params, self.config, key, self.hp,
                        static_argnums=(0, 1, 3))

    def act(self, state: PPOState, obs: Observation, key: jax.Array):
        """Buttons sampled from the policy; `info`: their log-probability and the value."""
        logits, value = policy_value(self.model, state.params, obs.frames)
        action = sample_action(key, logits)
        return state, action, {"log_prob": log_prob(logits, action), "value": value}

    def transition(self, params, c: tuple[Games, jax.Array]):
        """One step of B games on the rollout carry `c` = (games, key). Returns (next c, record
        of the step)."""
        games, key = c
        key, k_act, k_game = jax.random.split(key, 3)
        view = PPOState(params=params, opt_state=None, games=games, key=key, step=None)
        _, action, info = self.act(view, observe(games), k_act)
        after, _, reward, stats = step_games(self.game, self.env_params, games, action, k_game, self.model)
        record = {"obs": games.obs, "action": action, **info, "reward": reward, "done": stats["done"],
                  "finished_return": stats["finished_return"], "finished_length": stats["finished_length"]}
        return (after, key), record

    def collect(self, state: PPOState):
        """T steps of the B games with the state's parameters (a `lax.scan` of `transition`).
        Returns (state with the games and key moved on; (records `[T, B, ...]`, value of the
        last frame `[B]`))."""
        (games, key), traj = jax.lax.scan(lambda c, _: self.transition(state.params, c),
                                          (state.games, state.key), None, length=self.config.unroll)
        _, last_value = policy_value(self.model, state.params, games.obs)
        return state.replace(games=games, key=key), (traj, last_value)

    def update(self, state: PPOState, batch):
        """GAE on the rollout `batch` = (records, last value), then `epochs` x `minibatches`
        updates. Returns (state, metrics)."""
        traj, last_value = batch
        hp = self.hp
        advantages = gae(traj["reward"], traj["value"], traj["done"], last_value, hp.gamma, hp.gae_lambda)
        key, k_update = jax.random.split(state.key)
        params, opt_state, per_update = update(self.model, self.config, state.params, state.opt_state,
                                               flatten_rollout(traj, advantages), hp, k_update)
        new_state = state.replace(params=params, opt_state=opt_state, key=key, step=state.step + 1)
        metrics = {
            **reduce_updates(per_update),
            "reward": jnp.mean(traj["reward"]),
            "episodes": jnp.sum(traj["done"]),
            "return_sum": jnp.sum(traj["finished_return"]),
            "length_sum": jnp.sum(traj["finished_length"]),
            "action_mean": jnp.mean(traj["action"], axis=(0, 1)),
        }
        return new_state, metrics

    def train_step(self, state: PPOState):
        return self.update(*self.collect(state))

    def policy(self, state: PPOState):
        return ppo_policy(self.model, state.params)

    def watched(self, state: PPOState):
        return state.params


# --------------------------------------------------------------------------- playing


@functools.lru_cache(maxsize=32)
def ppo_policy_fns(arch: ArchConfig, greedy: bool = True):
    """(init, step) of a PPO policy for one game, its parameters an argument (`init(key,
    params)`, `step(key, state, obs, params)`; one pair per architecture, so a program playing it
    compiles once for any parameters): the game's frame is seen as `model_obs` shows it; greedy
    presses a button when its probability exceeds 0.5, otherwise each button is sampled with the
    key given to `step`."""

    def init(key, params):
        del key, params
        return jnp.zeros((), jnp.float32)

    def step(key, state, obs, params):
        logits, _ = policy_value(arch, params, model_obs(obs, arch)[None])
        action = (logits[0] > 0.0).astype(jnp.float32) if greedy else sample_action(key, logits[0])
        return action, state

    return init, step


def ppo_policy(arch: ArchConfig, params, greedy: bool = True):
    """The trained policy, `(init, step, params)`, in the form of `cdrl.evaluation.play`
    (`play(..., params=)`, `compare_policies`)."""
    return (*ppo_policy_fns(arch, greedy), params)
