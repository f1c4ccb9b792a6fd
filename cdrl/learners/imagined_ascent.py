"""`imagined_ascent` (alias `imagine`): the thesis's ascent in the model's imagination.

From every real state of a replayed chunk the model imagines `horizon` steps, fed its own
predictions and the controller's actions ã as they are (deterministic). The controller ascends
the discounted predicted reward of those steps, its gradient taken through the model.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from cdrl.learners.imagination import ImaginationConfig, imagine
from cdrl.learners.replay_base import ReplayLearner, ReplayState, starts


class ImaginedAscent(ReplayLearner):
    """See the module docstring. `model` is a controller variant that predicts reward."""

    name = "imagined_ascent"

    @classmethod
    def from_run(cls, cfg, model, game, env_params) -> "ImaginedAscent":
        config = ImaginationConfig(num_envs=cfg.batch, unroll=cfg.unroll, replay=cfg.replay,
                                   model_updates=cfg.model_updates, horizon=cfg.horizon)
        return cls(model, game, config, cls.hparams(cfg, model), env_params)

    def objective(self, params, carry, action, frame, key):
        """Minus the mean discounted imagined reward (the controller's loss), and its terms."""
        traj = imagine(self.model, self.config.horizon, params, carry, action, frame, key, sample=False)
        discount = self.hp.gamma ** jnp.arange(self.config.horizon, dtype=jnp.float32)[:, None]
        objective = jnp.mean(jnp.sum(discount * traj["reward"], axis=0))
        return -objective, {"imagined_return": objective}

    def replayed_update(self, state: ReplayState, chunk, carry, key, on):
        begin = starts(self.model, jax.lax.stop_gradient(state.model.params), chunk, carry)

        def losses(p, critic):
            actor, terms = self.objective(p, *begin, key)
            return self.hp.ascent * on * actor + jnp.zeros(()), (actor, terms)

        return self.controller_step(state, losses)
