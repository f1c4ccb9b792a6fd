"""`onpolicy_ac` (alias `real`): an actor-critic on the world model's states along the chunk
just played, from its real rewards.

The model gives the controller its features; the credit comes from the game. With scope `all`
the actor's and the critic's gradients also shape the core and the encoder.

With a critic plan (`critic_plan`), the buttons pressed look one step ahead through the model.
Each of the eight button combinations a is pressed with the real frame o_t in the model and
scored Q(a) = r̂(a) + γ V(h_t(a)): the predicted reward and the critic's value of the model's
state after it. The policy presses argmax_a log π(a) + κ Q(a), π the controller's buttons, κ
`plan_weight`; it is the one-step improvement π(a) exp(κ Q(a)) of the controller, taken
greedily. `eval` plans in the noise-free policy only; `always` also draws the buttons of
training from π_ε(a) exp(κ Q(a)) (π_ε: with the exploration), so the critic values the planner
and the clipped update moves the controller towards the plans that paid.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from cdrl.data.frames import model_obs
from cdrl.data.stream import Chunk
from cdrl.learners.game_batch import Observation
from cdrl.learners.mpc_planner import plan_rollouts
from cdrl.learners.ppo import clipped_surrogate
from cdrl.learners.replay_base import (ReplayConfig, ReplayLearner, ReplayState, button_entropy, button_log_prob,
                                       critic_value)
from cdrl.models.base import BUTTON_COMBOS, StepInput, Variant
from cdrl.training.lookahead import lambda_returns
from cdrl.options import CONTROL
from cdrl.training.step import step_inputs

SCOPES = ("controller", "all")
# Where the critic plan presses the buttons: nowhere, in the noise-free policy, or in training too.
CRITIC_PLANS = ("off", "eval", "always")


@dataclasses.dataclass(frozen=True)
class OnPolicyConfig(ReplayConfig):
    """`ReplayConfig`, the passes of the clipped update over each chunk played, and what its
    gradient changes: the controller, or `all` (the core and the encoder too)."""

    epochs: int = CONTROL.ppo_epochs
    scope: str = CONTROL.scope
    critic_plan: str = CONTROL.critic_plan

    def __post_init__(self):
        super().__post_init__()
        if self.scope not in SCOPES:
            raise ValueError(f"scope must be controller or all, got {self.scope!r}")
        if self.critic_plan not in CRITIC_PLANS:
            raise ValueError(f"critic_plan must be one of {', '.join(CRITIC_PLANS)}, got {self.critic_plan!r}")


def plan_values(variant: Variant, params, critic, carry, x: StepInput, gamma):
    """`[B, C]`: Q(a) = r̂(a) + γ V(h_t(a)) of every button combination a (`BUTTON_COMBOS`)
    pressed with the real step `x` (its action ignored) from the model's state `carry` before it:
    the predicted reward and the critic's value of the state after (`plan_rollouts`, one step).
    The critic's value at h_t is of the returns after a_t's reward, so the two add up to a_t's."""
    rewards, h, _ = plan_rollouts(variant, params, carry, x, 1)
    return (rewards[:, 0] + gamma * critic_value(critic, h[:, 0])).T


def prior_log_probs(variant: Variant, params, carry, explore=0.0):
    """`[B, C]`: log π(a) of every button combination under the controller's output from the
    model's state `carry` (independent buttons, each drawn uniformly with chance `explore`)."""
    probs = variant.heads(params, variant.fc(params, variant.features(carry)))["action"]
    probs = (1.0 - explore) * probs + explore * 0.5
    return button_log_prob(probs[:, None, :], jnp.asarray(BUTTON_COMBOS)[None])


def tilted_scores(variant: Variant, params, critic, carry, x: StepInput, gamma, kappa, explore=0.0):
    """`[B, C]`: log π(a) + κ Q(a) of every button combination (`prior_log_probs`, `plan_values`)."""
    return (prior_log_probs(variant, params, carry, explore)
            + kappa * plan_values(variant, params, critic, carry, x, gamma))


def critic_plan_fns(variant: Variant):
    """(init, step) of the noise-free critic plan for one game, in the form of
    `cdrl.evaluation.play`: it presses argmax_a log π(a) + κ Q(a) (`tilted_scores`); at an
    episode's first frame nothing, as the controller does. Its
    parameters are `{"model", "critic", "gamma", "kappa"}`, traced: one program for any."""

    def init(key, params):
        del key, params
        return {"carry": variant.init_carry(1), "is_first": jnp.ones((1,), bool)}

    def step(key, state, obs, params):
        del key
        x = StepInput(obs=model_obs(obs, variant.arch)[None], action=jnp.zeros((1, variant.arch.action_dim)),
                      is_first=state["is_first"])
        model = params["model"]
        scores = tilted_scores(variant, model, params["critic"], state["carry"], x, params["gamma"], params["kappa"])
        best = jnp.where(state["is_first"][:, None], 0.0, jnp.asarray(BUTTON_COMBOS)[jnp.argmax(scores, -1)])
        carry, _ = variant.step(model, state["carry"], x.replace(action=best))
        return best[0], {"carry": carry, "is_first": jnp.zeros((1,), bool)}

    return init, step


def onpolicy_returns(h_values, reward, is_first, first_after, gamma, lam):
    """The λ-returns and the mask of the decisions of a chunk played, for `onpolicy_ac`.

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


class OnPolicyAC(ReplayLearner):
    """See the module docstring. `model` is a controller variant that predicts reward."""

    name = "onpolicy_ac"

    @classmethod
    def from_run(cls, cfg, model, game, env_params) -> "OnPolicyAC":
        config = OnPolicyConfig(num_envs=cfg.batch, unroll=cfg.unroll, replay=cfg.replay,
                                model_updates=cfg.model_updates, epochs=cfg.ppo_epochs, scope=cfg.scope,
                                critic_plan=cfg.critic_plan)
        return cls(model, game, config, cls.hparams(cfg, model), env_params)

    def act(self, state: ReplayState, obs: Observation, key: jax.Array, explore=None):
        """As every replay learner's, but with the critic plan `always` the buttons executed at t
        are drawn now, from π_ε(a) exp(κ Q(a)) (the controller's output at t − 1 the prior, Q
        with o_t), and nothing at an episode's first frame."""
        if self.config.critic_plan != "always":
            return super().act(state, obs, key, explore)
        explore = self.exploration(state) if explore is None else explore
        params, carry = state.model.params, state.model.carry
        x = StepInput(obs=obs.frames, action=state.action, is_first=obs.is_first)
        scores = tilted_scores(self.model, params, state.critic, carry, x, self.hp.gamma, self.hp.plan_weight, explore)
        drawn = jnp.asarray(BUTTON_COMBOS)[jax.random.categorical(key, scores)]
        executed = jnp.where(obs.is_first[:, None], 0.0, drawn)
        carry, out = self.model.step(params, carry, x.replace(action=executed))
        return state.replace(model=state.model.replace(carry=carry), action=executed), executed, out

    def policy(self, state: ReplayState):
        if self.config.critic_plan == "off":
            return super().policy(state)
        return (*critic_plan_fns(self.model), {"model": state.model.params, "critic": state.critic,
                                               "gamma": self.hp.gamma, "kappa": self.hp.plan_weight})

    def played_update(self, state: ReplayState, chunk: dict, carry0, explore, on):
        """The controller and the critic on the chunk just played, from its real rewards.

        The states are the model's own h_t along the chunk, teacher-forced on the executed buttons
        from `carry0` (the controller's parameters do not change them). The critic V(h_t) learns
        the λ-returns of the real rewards (`onpolicy_returns`); the controller is updated by PPO's
        clipped surrogate on the probability it drew the executed buttons with, (1 - ε) ã + ε / 2,
        the advantages normalised over the chunk, plus an entropy bonus on ã; `epochs` passes over
        the chunk. With scope `controller` no gradient reaches the world model: it learns its frames
        only, and the controller reads what it has learnt (h as recorded while acting). With scope
        `all` the actor's and the critic's gradients reach the core and the encoder too, stepped
        by the controller's optimiser beside the model's own updates on its frames."""
        variant, hp = self.model, self.hp
        everything = self.config.scope == "all"
        recorded = Chunk(obs=chunk["obs"], next_obs=chunk["next_obs"], action=chunk["action"], reward=chunk["reward"],
                         is_first=chunk["is_first"])

        def features(params):
            if not everything:
                return jax.lax.stop_gradient(chunk["h"])  # [T, B, H]

            def body(c, x):
                c, _ = variant.step(params, c, x)
                return c, variant.features(c)

            return jax.lax.scan(body, carry0, step_inputs(recorded))[1]

        executed = chunk["action"][1:]  # a_{t+1}, t < T - 1

        def probs_of(params, h):
            a = variant.heads(params, variant.fc(params, h[:-1]))["action"]
            return (1.0 - explore) * a + explore * 0.5, a

        h0 = jax.lax.stop_gradient(chunk["h"])
        old_logp = jax.lax.stop_gradient(button_log_prob(probs_of(state.model.params, h0)[0], executed))
        rets, valid = onpolicy_returns(critic_value(state.critic, h0), chunk["reward"], chunk["is_first"],
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
            return self.controller_step(state, losses, everything)

        state, terms = jax.lax.scan(epoch, state, None, length=self.config.epochs)
        return state, jax.tree.map(lambda x: x[-1], terms)
