"""`thesis_ascent` (alias `rollout`): the thesis's online learner, gradient ascent on the
predicted reward through the real chunk (its section 6.1, future work).

One train step is a `lax.scan` over T steps in which the model acts (its controller output
ã is executed, with exploration noise) and the B games answer; then the loss, the gradients
and the optimiser update. The games' outputs enter the graph behind a stop-gradient (the
game is not differentiable; the model's predictions are), and the model's own action output
keeps its gradient as it is fed back (straight-through past the noise and the clip to [0, 1]).

Objective: observation BCE + reward_weight * reward MSE − ascent * mean predicted reward.
The ascent term is on after `warmup_steps` updates. It may change the controller D_a only
(scope `controller`) or every parameter (scope `all`, the thesis's literal wording, which
also lets the model simply predict more reward unless the prediction loss holds it back).
The scope is a traced number, so one compiled program serves both. The predicted reward is
summed over the T-step chunk: T is the ascent's horizon.

The ascent differentiates through acting, so its `update` takes the chunk with its backward
pass (`AscentBatch`), not recorded arrays.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable

import flax.struct
import jax
import jax.numpy as jnp

from cdrl.evaluation.play import controller_policy
from cdrl.learners.api import Learner
from cdrl.learners.game_batch import Games, Observation, copy_scores, observe, reset_games, step_games
from cdrl.models.base import StepInput, Variant, bce_with_logits
from cdrl.options import CONTROL, DEFAULT_RECIPE, FAMILY_OVERRIDES, RECIPES, OptimOptions
from cdrl.training.optim import OptHParams, init_opt_state
from cdrl.training.step import TrainState, guarded_update, run_once

SCOPES = ("controller", "all")


@dataclasses.dataclass(frozen=True)
class AscentConfig:
    """Static shape: B games, T steps per chunk (defaults: a run's, `cdrl.options`)."""

    num_envs: int = FAMILY_OVERRIDES["ascent"][DEFAULT_RECIPE]["batch"]
    unroll: int = FAMILY_OVERRIDES["ascent"][DEFAULT_RECIPE]["unroll"]

    def __post_init__(self):
        if self.num_envs < 1 or self.unroll < 1:
            raise ValueError(f"num_envs and unroll must be >= 1, got {self.num_envs} and {self.unroll}")


@flax.struct.dataclass
class AscentHParams:
    """Traced numbers (a `vmap` sweep can vary any of them)."""

    opt: OptHParams  # the optimiser (SGD with momentum by default)
    ascent: jax.Array  # lambda: weight of the reward-ascent term
    reward_weight: jax.Array
    noise_std: jax.Array  # exploration noise on ã when acting
    noise_decay: jax.Array  # per update: std_k = noise_std * noise_decay ** k
    warmup_steps: jax.Array  # updates of pure model learning before the ascent term
    diverge_threshold: jax.Array
    ascent_all: jax.Array  # 1: the ascent may change every parameter ("all"); 0: the controller only

    @classmethod
    def create(cls, lr=FAMILY_OVERRIDES["ascent"][DEFAULT_RECIPE]["lr"], momentum=RECIPES[DEFAULT_RECIPE]["momentum"],
               ascent=CONTROL.ascent, reward_weight=RECIPES[DEFAULT_RECIPE]["reward_weight"],
               noise_std=CONTROL.noise_std, noise_decay=CONTROL.noise_decay, warmup_steps=CONTROL.warmup_steps,
               diverge_threshold=OptimOptions.diverge_threshold, scope=CONTROL.scope,
               opt: OptHParams | None = None) -> "AscentHParams":
        """The defaults are a run's (`cdrl.options`). `opt`: the optimiser's numbers (default:
        SGD with `lr` and `momentum`, which it replaces)."""
        if scope not in SCOPES:
            raise ValueError(f"unknown ascent scope {scope!r}; choose one of {SCOPES}")
        f32 = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
        opt = opt if opt is not None else OptHParams.create(lr=lr, momentum=momentum)
        return cls(opt, f32(ascent), f32(reward_weight), f32(noise_std), f32(noise_decay),
                   f32(warmup_steps), f32(diverge_threshold), f32(scope == "all"))


@flax.struct.dataclass
class AscentState:
    train: TrainState  # params, optimiser state, model carry, update count
    games: Games
    action: jax.Array  # [B, A]: ã_t, the model's output to execute next (void where an episode starts)
    key: jax.Array


@flax.struct.dataclass
class Rollout:
    """What acting carries from one step to the next: the model's recurrent state, the games,
    ã_t (the model's output, executed next) and the PRNG key."""

    carry: Any
    games: Games
    action: jax.Array
    key: jax.Array


@flax.struct.dataclass
class AscentBatch:
    """A chunk played with the parameters being differentiated: its losses, the backward pass
    of (model loss, mean predicted reward) to the parameters, the state after it, its terms,
    the game statistics and the exploration noise it was played with."""

    model_loss: jax.Array
    pred_reward: jax.Array
    vjp: Callable = flax.struct.field(pytree_node=False)
    after: AscentState = None
    terms: Any = None
    stats: Any = None
    noise_std: jax.Array = None


def chunk_objective(variant: Variant, outs, stats, hp: AscentHParams):
    """(model loss, mean predicted reward, loss terms) of a chunk's outputs `[T, B, ...]`.
    Besides the weighted terms, `copy_bce` and `target_entropy` (weight 0) score copying the
    last frame and the floor on the same frames, for the excess ratio of the predictions."""
    target = jax.lax.stop_gradient(outs["target"])
    terms = {"obs_bce": bce_with_logits(outs["logits"], target), **copy_scores(outs["obs"], target)}
    if variant.predicts_reward:
        terms["reward_mse"] = jnp.mean(jnp.square(outs["pred_reward"] - stats["reward"]))
    model_loss = terms["obs_bce"] + hp.reward_weight * terms.get("reward_mse", 0.0)
    return model_loss, jnp.mean(outs["pred_reward"]), terms


class ThesisAscent(Learner):
    """The thesis's online learner; see the module docstring. `model` is a controller variant."""

    name = "thesis_ascent"
    extras = ("noise_std", "ascent_on")
    recipe_family = "ascent"
    donate_state = False

    @classmethod
    def from_run(cls, cfg, model, game, env_params) -> "ThesisAscent":
        hp = AscentHParams.create(opt=cfg.opt_hparams(), ascent=cfg.ascent, reward_weight=cfg.reward_weight,
                                  noise_std=cfg.noise_std, noise_decay=cfg.noise_decay,
                                  warmup_steps=cfg.warmup_steps, diverge_threshold=cfg.diverge_threshold,
                                  scope=cfg.scope)
        return cls(model, game, AscentConfig(num_envs=cfg.batch, unroll=cfg.unroll), hp, env_params)

    def init(self, key: jax.Array) -> AscentState:
        """Fresh parameters, optimiser state, carries and B new games."""
        if not self.model.has_controller:
            raise ValueError(f"variant {self.model.name!r} has no controller; online training needs one of "
                             "action_loop, reward_prediction, final_proposal")
        return run_once(_init, self.model, self.game, self.env_params, self.config, key, self.hp,
                        static_argnums=(0, 1, 3))

    def noise(self, state: AscentState) -> jax.Array:
        """The exploration noise's std at the state's update."""
        return self.hp.noise_std * self.hp.noise_decay ** state.train.step.astype(jnp.float32)

    def act(self, state: AscentState, obs: Observation, key: jax.Array, noise_std=None):
        """Execute ã_t plus Gaussian noise (clipped to [0, 1]); the model sees o_t and the
        executed value, its gradient going to ã_t (straight-through), and outputs ã_{t+1}.
        `info`: the model's outputs."""
        noise_std = self.noise(state) if noise_std is None else noise_std
        pending = jnp.where(obs.is_first[:, None], 0.0, state.action)
        noisy = jnp.clip(pending + noise_std * jax.random.normal(key, pending.shape), 0.0, 1.0)
        a_in = pending + jax.lax.stop_gradient(noisy - pending)  # the executed value, gradient to ã
        carry, out = self.model.step(state.train.params, state.train.carry,
                                     StepInput(obs=obs.frames, action=a_in, is_first=obs.is_first))
        return state.replace(train=state.train.replace(carry=carry), action=out["action"]), noisy, out

    def transition(self, params, step, noise_std, c: Rollout):
        """One step of acting and predicting with `params`. Returns (rollout after it, (model
        outputs, game statistics)), the game's outputs stop-gradiented."""
        key, k_noise, k_game = jax.random.split(c.key, 3)
        obs = observe(c.games)
        view = AscentState(train=TrainState(params=params, opt_state=None, carry=c.carry, step=step),
                           games=c.games, action=c.action, key=key)
        view, executed, out = self.act(view, obs, k_noise, noise_std)
        games, nxt, reward, stats = step_games(self.game, self.env_params, c.games, executed, k_game,
                                               self.model.arch)
        outs = {"logits": out["logits"], "obs": obs.frames, "target": nxt,
                "pred_reward": out["reward"] if self.model.predicts_reward else jnp.zeros_like(reward)}
        return Rollout(carry=view.train.carry, games=games, action=view.action, key=key), (outs, stats)

    def collect(self, params, state: AscentState):
        """Act and predict for T steps with `params`. Returns ((model loss, mean predicted
        reward), (state after the chunk, terms, game statistics, noise std))."""
        noise_std = self.noise(state)
        start = Rollout(carry=jax.lax.stop_gradient(state.train.carry), games=state.games, action=state.action,
                        key=state.key)
        end, (outs, stats) = jax.lax.scan(lambda c, _: self.transition(params, state.train.step, noise_std, c),
                                          start, None, length=self.config.unroll)
        model_loss, pred_reward, terms = chunk_objective(self.model, outs, stats, self.hp)
        after = state.replace(train=state.train.replace(carry=end.carry), games=end.games,
                              action=jax.lax.stop_gradient(end.action), key=end.key)
        return (model_loss, pred_reward), (after, terms, stats, noise_std)

    def update(self, state: AscentState, batch: AscentBatch):
        """The gradient of model_loss − lam * pred_reward, the ascent on D_a's parameters only
        unless `ascent_all`. One backward pass gives every parameter the model's gradient and
        the ascent's share that reaches all of them (lam * ascent_all); a second adds the rest
        of the ascent to D_a, and only D_a's gradient is taken from it, so XLA leaves the
        others' computation out. There is no rest before the ascent is on or with
        `ascent_all`: the second pass is then skipped (under `vmap` both branches run)."""
        hp, variant, params = self.hp, self.model, state.train.params
        active = (state.train.step.astype(jnp.float32) >= hp.warmup_steps).astype(jnp.float32)
        lam = hp.ascent * active
        rest = -lam * (1.0 - hp.ascent_all)
        (shared,) = batch.vjp((jnp.ones(()), -lam * hp.ascent_all))

        def reward_gradient():
            (reward,) = batch.vjp((jnp.zeros(()), jnp.ones(())))
            return {k: reward[k] for k in variant.controller_groups}

        def no_rest():
            return {k: jax.tree.map(jnp.zeros_like, params[k]) for k in variant.controller_groups}

        reward = jax.lax.cond(rest != 0.0, reward_gradient, no_rest)
        grads = _add_ascent_rest(variant, shared, reward, rest)
        new_params, opt_state, guard = guarded_update(hp.opt, hp.diverge_threshold, params, state.train.opt_state,
                                                      grads, batch.model_loss)
        # A refused update keeps the old parameters; the games go on.
        train = batch.after.train.replace(params=new_params, opt_state=opt_state, step=state.train.step + 1)
        stats = batch.stats
        metrics = {
            "loss": batch.model_loss - lam * batch.pred_reward,
            "terms": {**batch.terms, "pred_reward": batch.pred_reward},
            "reward": jnp.mean(stats["reward"]),
            "episodes": jnp.sum(stats["done"]),
            "return_sum": jnp.sum(stats["finished_return"]),
            "length_sum": jnp.sum(stats["finished_length"]),
            "action_mean": jnp.mean(stats["action"], axis=(0, 1)),
            "noise_std": batch.noise_std,
            "ascent_on": active,
            **guard,
        }
        return batch.after.replace(train=train), metrics

    def train_step(self, state: AscentState):
        (model_loss, pred_reward), vjp, (after, terms, stats, noise_std) = jax.vjp(
            lambda p: self.collect(p, state), state.train.params, has_aux=True)
        return self.update(state, AscentBatch(model_loss, pred_reward, vjp, after, terms, stats, noise_std))

    def policy(self, state: AscentState):
        return controller_policy(self.model, state.train.params)

    def watched(self, state: AscentState):
        return state.train.params

    def with_world_model(self, state: AscentState, params) -> AscentState:
        return state.replace(train=state.train.replace(params=params))


def _init(variant, game, env_params, cfg, key, hp) -> AscentState:
    k_params, k_env, k_run = jax.random.split(key, 3)
    params = variant.init(k_params)
    b = cfg.num_envs
    train = TrainState(params=params, opt_state=init_opt_state(hp.opt, params),
                       carry=variant.init_carry(b), step=jnp.zeros((), jnp.int32))
    return AscentState(train=train, games=reset_games(game, env_params, k_env, b, variant.arch),
                       action=jnp.zeros((b, variant.arch.action_dim)), key=k_run)


def _add_ascent_rest(variant: Variant, shared, reward, rest):
    """`shared` plus `rest` times `reward` (D_a's groups only) on the controller D_a's parameters;
    `shared` elsewhere."""
    return {k: (jax.tree.map(lambda s, r: s + rest * r, v, reward[k]) if k in variant.controller_groups else v)
            for k, v in shared.items()}
