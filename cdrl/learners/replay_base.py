"""What the learners with a replay buffer share: acting, the buffer, the world model's updates
and the controller's optimiser step.

`cdrl.learners.thesis_ascent` learns from each chunk once, the predicted reward's gradient
reaching the controller through the real chunk. These learners separate the world model from
the controller, as world-model agents do (Dreamer's train ratio), keeping the thesis's model
and heads. One train step:

1. act: B games play T steps; the model sees o_t and the executed a_t and outputs ã_{t+1}
   (the controller D_a on the core's output). The buttons executed next are drawn from
   Bernoulli(p) with p = (1 - ε) ã + ε / 2 (ε: the exploration, decaying per update); the
   chunk (frames, executed buttons, rewards, episode starts, the model's carry at its start)
   is written into a ring buffer of the last `replay` chunks;
2. `played_update`: a learner may learn from the chunk just played (on-policy);
3. `model_updates` times: draw a chunk from the buffer; the world model takes one update on it,
   as offline training makes it (`cdrl.training.step.chunk_loss`: teacher-forced on the
   executed buttons, from the carry stored with the chunk, behind the divergence guard), with
   its own optimiser; then `replayed_update` lets the learner update the controller from that
   chunk's states.

The controller (the FC layer's action-code columns and D_a, `controller_mask`) and a critic
step with their own optimiser (Adam). The controller's objective is off for `warmup_steps`
updates, while the model learns alone (a critic learns from the start).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, ClassVar

import flax.struct
import jax
import jax.numpy as jnp

from cdrl.data.frames import pixel_bce
from cdrl.data.stream import Chunk
from cdrl.evaluation.play import controller_policy
from cdrl.learners.api import Learner
from cdrl.learners.game_batch import Games, Observation, copy_scores, observe, reset_games, step_games
from cdrl.models import nets
from cdrl.options import CONTROL, DEFAULT_RECIPE, FAMILY_OVERRIDES
from cdrl.models.base import StepInput, Variant
from cdrl.training import lookahead
from cdrl.training.optim import HParams, OptHParams, init_opt_state
from cdrl.training.step import TrainState, chunk_loss, guarded_update, run_once, step_inputs

CRITIC_HIDDEN = 128


@dataclasses.dataclass(frozen=True)
class ReplayConfig:
    """Static shape: B games x T steps per chunk, `replay` chunks kept, `model_updates` per
    chunk (defaults: a run's, `cdrl.options`)."""

    num_envs: int = FAMILY_OVERRIDES["replay"][DEFAULT_RECIPE]["batch"]
    unroll: int = FAMILY_OVERRIDES["replay"][DEFAULT_RECIPE]["unroll"]
    replay: int = CONTROL.replay
    model_updates: int = CONTROL.model_updates

    def __post_init__(self):
        for f in dataclasses.fields(self):
            if isinstance(getattr(self, f.name), int) and getattr(self, f.name) < 1:
                raise ValueError(f"{f.name} must be >= 1, got {getattr(self, f.name)}")


@flax.struct.dataclass
class ReplayHParams:
    """Traced numbers (a `vmap` sweep can vary any of them)."""

    model: HParams  # the model's optimiser, loss weights and divergence threshold
    ctrl_opt: OptHParams  # the heads' optimiser: the controller's, the critic's and the reward head's
    ascent: jax.Array  # weight of the controller's objective (0: the model learns alone)
    explore: jax.Array  # ε at update 0: the chance a button is drawn uniformly
    explore_decay: jax.Array  # per update: ε_k = explore * explore_decay ** k
    warmup_steps: jax.Array  # updates before the controller's objective is on
    gamma: jax.Array  # discount
    lam: jax.Array  # λ of the critics' λ-returns
    entropy: jax.Array  # the actor's entropy bonus
    clip_eps: jax.Array  # `onpolicy_ac`: clip range of the probability ratio
    plan_weight: jax.Array  # `onpolicy_ac` with a critic plan: κ, the weight of Q(a) against log π(a)

    @classmethod
    def create(cls, model: HParams, ctrl_opt: OptHParams | None = None, ascent=CONTROL.ascent,
               explore=CONTROL.noise_std, explore_decay=CONTROL.noise_decay, warmup_steps=CONTROL.warmup_steps,
               gamma=CONTROL.gamma, lam=CONTROL.gae_lambda, entropy=CONTROL.entropy_coef,
               clip_eps=CONTROL.clip_eps, plan_weight=CONTROL.plan_weight) -> "ReplayHParams":
        """The defaults are a run's (`cdrl.options`); `ctrl_opt` is Adam at `ctrl_lr` with the
        gradient norm clipped at 100 unless given."""
        f32 = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
        ctrl_opt = ctrl_opt if ctrl_opt is not None else OptHParams.create("adam", lr=CONTROL.ctrl_lr, grad_clip=100.0)
        return cls(model, ctrl_opt, f32(ascent), f32(explore), f32(explore_decay), f32(warmup_steps), f32(gamma),
                   f32(lam), f32(entropy), f32(clip_eps), f32(plan_weight))


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
class ReplayState:
    model: TrainState  # the world model: params (controller included), its optimiser, acting carry, updates
    ctrl_opt_state: Any  # the controller's optimiser state
    reward_opt_state: Any  # the reward head's optimiser state (the heads' optimiser)
    critic: Any  # the critic's parameters (unused by `imagined_ascent`)
    critic_opt_state: Any
    replay: Replay
    games: Games
    action: jax.Array  # [B, A]: the buttons executed next (void where an episode starts)
    key: jax.Array


def draw_buttons(key, probs: jax.Array) -> jax.Array:
    """Buttons pressed (1.0) with probability `probs`, else released (0.0)."""
    return (jax.random.uniform(key, probs.shape) < probs).astype(jnp.float32)


def button_entropy(probs: jax.Array) -> jax.Array:
    """The entropy of independent Bernoulli(`probs`) buttons, summed over the last axis."""
    p = jnp.clip(probs, 1e-6, 1 - 1e-6)
    return -jnp.sum(p * jnp.log(p) + (1 - p) * jnp.log1p(-p), axis=-1)


def button_log_prob(probs: jax.Array, buttons: jax.Array) -> jax.Array:
    """log P(`buttons`) under independent Bernoulli(`probs`), summed over the last axis."""
    p = jnp.clip(probs, 1e-6, 1 - 1e-6)
    return jnp.sum(buttons * jnp.log(p) + (1.0 - buttons) * jnp.log1p(-p), axis=-1)


def critic_value(critic, h):
    return nets.mlp(critic, h, final_selu=False)[..., 0]


def starts(variant: Variant, params, chunk: Chunk, carry):
    """The real states a controller update starts from, flattened to `[T * B, ...]`: the
    model's carry after every step of `chunk`, its action output there (the buttons it would
    press next) and its predicted next frame (what imagination is fed first)."""

    def body(c, x):
        c, out = variant.step(params, c, x)
        return c, (c, out["action"], jax.nn.sigmoid(out["logits"]))

    _, (carries, actions, frames) = jax.lax.scan(body, carry, step_inputs(chunk))
    flat = lambda x: x.reshape((-1,) + x.shape[2:])  # noqa: E731
    return jax.tree.map(flat, carries), flat(actions), flat(frames)


def store(replay: Replay, chunk: dict, carry0) -> Replay:
    """Write a chunk (and the model's carry at its start) over the oldest one."""
    frames = jnp.concatenate([chunk["obs"], chunk["next_obs"][-1:]], axis=0)
    i = replay.cursor
    put = lambda buf, x: buf.at[i].set(x.astype(buf.dtype))  # noqa: E731
    return replay.replace(obs=put(replay.obs, jnp.round(frames * 255.0)), action=put(replay.action, chunk["action"]),
                          reward=put(replay.reward, chunk["reward"]), is_first=put(replay.is_first, chunk["is_first"]),
                          carry=jax.tree.map(put, replay.carry, carry0),
                          filled=jnp.minimum(replay.filled + 1, replay.obs.shape[0]),
                          cursor=(replay.cursor + 1) % replay.obs.shape[0])


class ReplayLearner(Learner):
    """The shared part of the learners with a replay buffer; see the module docstring. A
    learner overrides `played_update`, `replayed_update` or both."""

    extras = ("explore", "controller_on")
    # Outputs of `act` (its `info`, per game) whose mean over the chunk played is logged as a term.
    act_terms: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def hparams(cls, cfg, model) -> ReplayHParams:
        """The traced numbers of a run of `cfg` (`cdrl.runs.config.RunConfig`)."""
        return ReplayHParams.create(cfg.hparams(model), ctrl_opt=OptHParams.create("adam", lr=cfg.ctrl_lr,
                                                                                   grad_clip=100.0),
                                    ascent=cfg.ascent, explore=cfg.noise_std, explore_decay=cfg.noise_decay,
                                    warmup_steps=cfg.warmup_steps, gamma=cfg.gamma, lam=cfg.gae_lambda,
                                    entropy=cfg.entropy_coef, clip_eps=cfg.clip_eps, plan_weight=cfg.plan_weight)

    def init(self, key: jax.Array) -> ReplayState:
        if not self.model.has_controller:
            raise ValueError(f"variant {self.model.name!r} has no controller; online training needs one of "
                             "action_loop, reward_prediction, final_proposal")
        return run_once(_init, self.model, self.game, self.env_params, self.config, key, self.hp,
                        static_argnums=(0, 1, 3))

    def exploration(self, state: ReplayState) -> jax.Array:
        """ε at the state's update."""
        return self.hp.explore * self.hp.explore_decay ** state.model.step.astype(jnp.float32)

    def act(self, state: ReplayState, obs: Observation, key: jax.Array, explore=None):
        """Execute the pending buttons; the model sees o_t and them, and the buttons executed
        next are drawn from (1 - ε) ã_{t+1} + ε / 2. `info`: the model's outputs."""
        explore = self.exploration(state) if explore is None else explore
        executed = jnp.where(obs.is_first[:, None], 0.0, state.action)
        carry, out = self.model.step(state.model.params, state.model.carry,
                                     StepInput(obs=obs.frames, action=executed, is_first=obs.is_first))
        probs = (1.0 - explore) * out["action"] + explore * 0.5
        state = state.replace(model=state.model.replace(carry=carry), action=draw_buttons(key, probs))
        return state, executed, out

    def collect(self, state: ReplayState, explore):
        """T steps of acting (no gradient). Returns (state, the chunk's frames, executed buttons,
        rewards, episode starts and features `[T, B, ...]`, game statistics)."""

        def body(c, _):
            carry, games, action, key = c
            key, k_buttons, k_game = jax.random.split(key, 3)
            obs = observe(games)
            view = state.replace(model=state.model.replace(carry=carry), games=games, action=action)
            view, executed, out = self.act(view, obs, k_buttons, explore)
            carry = view.model.carry
            games, nxt, reward, stats = step_games(self.game, self.env_params, games, executed, k_game,
                                                   self.model.arch)
            record = {"obs": obs.frames, "next_obs": nxt, "action": executed, "reward": reward,
                      "is_first": obs.is_first, "h": self.model.features(carry)}
            scores = {"pred_reward": out["reward"], "obs_bce": pixel_bce(out["logits"], nxt),
                      **{k: out[k] for k in self.act_terms}}
            return (carry, games, view.action, key), (record, {**stats, **scores})

        (carry, games, action, key), (chunk, stats) = jax.lax.scan(
            body, (state.model.carry, state.games, state.action, state.key), None, length=self.config.unroll)
        state = state.replace(model=state.model.replace(carry=carry), games=games, action=action, key=key)
        return state, chunk, stats

    def model_update(self, state: ReplayState, chunk: Chunk, carry):
        """One guarded update of the model on `chunk` from `carry`, as offline training makes
        it; the controller's parameters get no gradient (they are the controller's to learn).
        The reward head's own parameters (`reward_mask`) step with the heads' optimiser (Adam),
        the rest with the model's (SGD): at the rates that train the frame predictor the reward
        head's squared error grows without bound, and at a weight small enough to hold it the
        head learns only the mean reward."""
        variant, hp, model = self.model, self.hp, state.model
        (loss, (_, terms, _)), grads = jax.value_and_grad(
            lambda p: chunk_loss(variant, p, carry, hp.model, chunk), has_aux=True)(model.params)
        grads = jax.tree.map(lambda g, m: g * (1.0 - m), grads, variant.controller_mask(model.params))
        look = lookahead.head_mask(model.params)  # the look-ahead heads: the heads' optimiser moves them
        heads = jax.tree.map(jnp.maximum, variant.reward_mask(model.params), look)
        model_grads = jax.tree.map(lambda g, m: g * (1.0 - m), grads, look)
        params, opt_state, guard = guarded_update(hp.model.opt, hp.model.diverge_threshold, model.params,
                                                  model.opt_state, model_grads, loss)
        head, head_state, head_guard = guarded_update(hp.ctrl_opt, hp.model.diverge_threshold, model.params,
                                                      state.reward_opt_state, grads, loss)
        params = jax.tree.map(lambda s, a, m: jnp.where(m > 0, a, s), params, head, heads)
        params = lookahead.update_target(params, hp.model.lookahead)
        guard = {**guard, "finite": guard["finite"] & head_guard["finite"],
                 "diverged": guard["diverged"] | head_guard["diverged"]}
        model = model.replace(params=params, opt_state=opt_state)
        return state.replace(model=model, reward_opt_state=head_state), {"loss": loss, "terms": terms, **guard}

    def controller_step(self, state: ReplayState, losses: Callable, everything: bool = False):
        """One step of the controller's optimiser (on its parameters only, or with `everything`
        on all of the model's) and of the critic's, on `losses(params, critic) -> (total,
        (actor loss, terms))`. Returns (state, terms with `controller_loss`)."""
        hp, params = self.hp, state.model.params
        (total, (actor, terms)), (g_params, g_critic) = jax.value_and_grad(losses, argnums=(0, 1), has_aux=True)(
            params, state.critic)
        mask = jax.tree.map(jnp.ones_like, params) if everything else self.model.controller_mask(params)
        g_params = jax.tree.map(lambda g, m: g * m, g_params, mask)
        new, opt_state, _ = guarded_update(hp.ctrl_opt, hp.model.diverge_threshold, params, state.ctrl_opt_state,
                                           g_params, total)
        new = jax.tree.map(lambda n, o, m: jnp.where(m > 0, n, o), new, params, mask)  # only the controller moves
        critic, critic_opt, _ = guarded_update(hp.ctrl_opt, hp.model.diverge_threshold, state.critic,
                                               state.critic_opt_state, g_critic, total)
        state = state.replace(model=state.model.replace(params=new), ctrl_opt_state=opt_state, critic=critic,
                              critic_opt_state=critic_opt)
        return state, {"controller_loss": actor, **terms}

    def played_update(self, state: ReplayState, chunk: dict, carry0, explore, on):
        """Learn from the chunk just played, before the model moves. Returns (state, terms);
        None: this learner does not."""
        return None

    def replayed_update(self, state: ReplayState, chunk: Chunk, carry, key, on):
        """Update the controller from a replayed chunk's states after the model's update on it.
        Returns (state, terms); None: this learner does not."""
        return None

    def update(self, state: ReplayState, batch):
        """Store the chunk played, learn from it, then `model_updates` times a model update and
        a controller update on a chunk drawn from the buffer. `batch` = (chunk, game statistics,
        carry at the chunk's start, ε, the key of the updates)."""
        chunk, stats, carry0, explore, k_model = batch
        step = state.model.step.astype(jnp.float32)
        state = state.replace(replay=store(state.replay, chunk, jax.lax.stop_gradient(carry0)))
        scores = copy_scores(chunk["obs"], chunk["next_obs"])
        on = (step >= self.hp.warmup_steps).astype(jnp.float32)
        played = self.played_update(state, chunk, carry0, explore, on)
        if played is not None:
            state, played_terms = played

        def learn(state: ReplayState, k):
            k_draw, k_controller = jax.random.split(k)
            replayed, carry = state.replay.chunk(jax.random.randint(k_draw, (), 0, state.replay.filled))
            state, model_m = self.model_update(state, replayed, carry)
            after = self.replayed_update(state, replayed, carry, k_controller, on)
            return (state, (model_m, {})) if after is None else (after[0], (model_m, after[1]))

        state, (model_m, ctrl_m) = jax.lax.scan(learn, state, jax.random.split(k_model, self.config.model_updates))
        state = state.replace(model=state.model.replace(step=state.model.step + 1))
        last = jax.tree.map(lambda x: x[-1], model_m)
        ctrl_terms = {**(played_terms if played is not None else {}), **jax.tree.map(jnp.mean, ctrl_m)}
        metrics = {
            "loss": last["loss"],
            # The model's scores on the chunk it acted in, before learning from it (obs_bce beside
            # copy_bce and target_entropy: the excess ratio of its predictions); the training
            # terms of its last update (on a replayed chunk) as model_<term>.
            "terms": {**{f"model_{k}": v for k, v in last["terms"].items()}, **scores, **ctrl_terms,
                      "obs_bce": jnp.mean(stats["obs_bce"]), "pred_reward": jnp.mean(stats["pred_reward"]),
                      **{k: jnp.mean(stats[k]) for k in self.act_terms}},
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

    def train_step(self, state: ReplayState):
        explore = self.exploration(state)
        carry0 = state.model.carry
        key, k_model = jax.random.split(state.key)
        state, chunk, stats = self.collect(state.replace(key=key), explore)
        return self.update(state, (chunk, stats, carry0, explore, k_model))

    def policy(self, state: ReplayState):
        return controller_policy(self.model, state.model.params)

    def watched(self, state: ReplayState):
        return state.model.params

    def with_world_model(self, state: ReplayState, params) -> ReplayState:
        return state.replace(model=state.model.replace(params=params))


def _init(variant, game, env_params, cfg, key, hp) -> ReplayState:
    if not variant.predicts_reward:
        raise ValueError(f"variant {variant.name!r} predicts no reward: a controller trained in imagination needs "
                         "reward_prediction or final_proposal")
    k_params, k_critic, k_env, k_run = jax.random.split(key, 4)
    params = lookahead.with_heads(variant, variant.init(k_params), k_params, hp.model.lookahead)
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
    return ReplayState(model=model, ctrl_opt_state=init_opt_state(hp.ctrl_opt, params),
                       reward_opt_state=init_opt_state(hp.ctrl_opt, params), critic=critic,
                       critic_opt_state=init_opt_state(hp.ctrl_opt, critic), replay=replay,
                       games=reset_games(game, env_params, k_env, b, variant.arch),
                       action=jnp.zeros((b, variant.arch.action_dim)), key=k_run)
