"""What the learners that train the controller in the model's imagination share: their static
shape, the imagined rollout itself, and their update from a replayed chunk's states."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from cdrl.learners.replay_base import ReplayConfig, ReplayLearner, ReplayState, draw_buttons, starts
from cdrl.models.base import Variant
from cdrl.options import CONTROL
from cdrl.training import lookahead


@dataclasses.dataclass(frozen=True)
class ImaginationConfig(ReplayConfig):
    """`ReplayConfig` and the imagined steps of each controller update."""

    horizon: int = CONTROL.horizon


def imagine(variant: Variant, horizon: int, params, carry, action, frame, key, sample: bool):
    """`horizon` steps of the model fed its own predictions from `carry`, taking the pending
    `action` (for closed loop − the error input is then zero: `FinalProposal.imagine_step`).
    With `sample` the buttons executed are drawn from Bernoulli(ã) (their probability and draw
    are returned); without, ã itself is fed in. Returns per step `[H, N]`: rewards r̃, features
    h, the action probabilities and the executed buttons."""

    def body(c, k):
        carry, action, frame = c
        executed = draw_buttons(k, action) if sample else action
        carry, out = variant.imagine_step(params, carry, frame, executed)
        frame = jax.nn.sigmoid(out["logits"]) if "logits" in out else frame
        return (carry, out["action"], frame), {"reward": out["reward"], "h": variant.features(carry),
                                               "probs": action, "buttons": executed}

    _, traj = jax.lax.scan(body, (carry, action, frame), jax.random.split(key, horizon))
    return traj


def lookahead_heads(look, params):
    """The look-ahead heads in `params` where the model trains them (`look`, its numbers), else None."""
    return params["lookahead"] if look is not None and "lookahead" in params else None


def imagination_config(cfg) -> ImaginationConfig:
    """The static shape of a run of `cfg` (`cdrl.runs.config.RunConfig`) that imagines."""
    return ImaginationConfig(num_envs=cfg.batch, unroll=cfg.unroll, replay=cfg.replay,
                             model_updates=cfg.model_updates, horizon=cfg.horizon)


def imagined_return(look, params, rewards, h, gamma, end=None):
    """Σ_k γ^k r̃_{k+1} + γ^H V_H of imagined steps (`rewards`, states `h`, leading axis H): the
    rewards and the value of the look-ahead heads where the model has them (`look`, the
    look-ahead's numbers, and `params["lookahead"]`); else the variant's own `rewards` and no
    value at the end. V_H is the return after the last step's reward: `end` where the caller
    has it (`mpc_planner`: the frame value of the last predicted frame), else
    `lookahead.value_after` (the value head's own counts that reward again)."""
    horizon = rewards.shape[0]
    discount = gamma ** jnp.arange(horizon, dtype=jnp.float32).reshape((horizon,) + (1,) * (rewards.ndim - 1))
    heads = lookahead_heads(look, params)
    if heads is None:
        return jnp.sum(discount * rewards, axis=0)
    rewards = lookahead.reward(heads, h, look)
    end = lookahead.value_after(heads, h[-1], look) if end is None else end
    return jnp.sum(discount * rewards, axis=0) + gamma ** horizon * end


class ImaginationLearner(ReplayLearner):
    """A replay learner whose controller learns from imagined rollouts that start at every real
    state of a replayed chunk. A learner gives `objective(params, critic, carry, action, frame,
    key) -> (actor loss, (critic loss, terms))`."""

    @classmethod
    def from_run(cls, cfg, model, game, env_params):
        return cls(model, game, imagination_config(cfg), cls.hparams(cfg, model), env_params)

    def objective(self, params, critic, carry, action, frame, key):
        raise NotImplementedError

    def replayed_update(self, state: ReplayState, chunk, carry, key, on):
        begin = starts(self.model, jax.lax.stop_gradient(state.model.params), chunk, carry)

        def losses(p, critic):
            actor, (critic_loss, terms) = self.objective(p, critic, *begin, key)
            return self.hp.ascent * on * actor + critic_loss, (actor, terms)

        return self.controller_step(state, losses)
