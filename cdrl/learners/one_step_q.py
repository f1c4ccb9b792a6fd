"""`one_step_q` (alias `value`): the buttons' values one model step ahead, learnt from real
returns.

The carry c_t has seen o_t and a_t; the controller's output there, ã_{t+1}, is the probability
of each button at t + 1. Q(c_t, a) is a critic W on the core after the model has taken a for
one step, so the action's effect goes through the world model's own dynamics. W learns the
λ-returns of a replayed chunk's real rewards. The controller ascends the expected Q under its
Bernoulli buttons, summed exactly over the 8 combinations, plus an entropy bonus.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from cdrl.data.stream import Chunk
from cdrl.models.base import BUTTON_COMBOS, Variant
from cdrl.learners.replay_base import (ReplayConfig, ReplayLearner, ReplayState, button_entropy,
                                       critic_value, starts)
from cdrl.training.lookahead import lambda_returns


def after_one_step(variant: Variant, params, carry, frame, buttons):
    """The model's state after one imagined step from `carry` (`[N, ...]`, its prediction
    `frame`) taking `buttons` `[N, A]`: what pressing them next leads to, as the model sees it."""
    return variant.imagine_step(params, carry, frame, buttons)[0]


def button_log_probs(probs: jax.Array) -> jax.Array:
    """log P(combo) `[8, N]` of every button combination under independent Bernoulli(`probs` `[N, 3]`)."""
    p = jnp.clip(probs, 1e-6, 1 - 1e-6)
    c = BUTTON_COMBOS[:, None, :]
    return jnp.sum(c * jnp.log(p)[None] + (1.0 - c) * jnp.log1p(-p)[None], axis=-1)


def value_objective(variant, hp, params, critic, chunk: Chunk, begin):
    """An action value read through the model's step, learnt from the real returns.

    The carry c_t has seen o_t and a_t; the controller's output there, ã_{t+1}, is the
    probability of each button at t + 1, before o_{t+1} is seen. Q(c_t, a) = W(h of the state
    after one imagined step from c_t taking a): the critic W reads the core after the model
    has taken the action, so the action's effect goes through the world model's own dynamics.
    W learns from the chunk's real rewards: for the executed a_{t+1}, the λ-return of the
    real r_{t+2}, r_{t+3}, ... bootstrapped with W of the same one-step states further along.
    The controller ascends the expected Q under its Bernoulli buttons, summed exactly over the
    8 combinations (no sampling), plus an entropy bonus; the Q values are behind a
    stop-gradient, so the gradient reaches the controller through its probabilities only."""
    carry, probs, frame = begin  # [T * B, ...], probs: ã_{t+1} with the gradient of the controller
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


class OneStepQ(ReplayLearner):
    """See the module docstring. `model` is a controller variant that predicts reward."""

    name = "one_step_q"

    @classmethod
    def from_run(cls, cfg, model, game, env_params) -> "OneStepQ":
        config = ReplayConfig(num_envs=cfg.batch, unroll=cfg.unroll, replay=cfg.replay, model_updates=cfg.model_updates)
        return cls(model, game, config, cls.hparams(cfg, model), env_params)

    def replayed_update(self, state: ReplayState, chunk: Chunk, carry, key, on):
        variant = self.model
        begin, _, frame = starts(variant, jax.lax.stop_gradient(state.model.params), chunk, carry)

        def losses(p, critic):
            probs = variant.heads(p, variant.fc(p, variant.features(begin)))["action"]
            actor, (critic_loss, terms) = value_objective(variant, self.hp, p, critic, chunk, (begin, probs, frame))
            return self.hp.ascent * on * actor + critic_loss, (actor, terms)

        return self.controller_step(state, losses)
