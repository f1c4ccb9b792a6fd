"""`imagined_ascent` (alias `imagine`): the thesis's ascent in the model's imagination.

From every real state of a replayed chunk the model imagines `horizon` steps, fed its own
predictions and the controller's actions ã as they are (deterministic). The controller ascends
the discounted predicted reward of those steps, its gradient taken through the model.
"""
from __future__ import annotations

import jax.numpy as jnp

from cdrl.learners.imagination import ImaginationLearner, imagine


class ImaginedAscent(ImaginationLearner):
    """See the module docstring. `model` is a controller variant that predicts reward."""

    name = "imagined_ascent"

    def objective(self, params, critic, carry, action, frame, key):
        """Minus the mean discounted imagined reward (the controller's loss); no critic."""
        traj = imagine(self.model, self.config.horizon, params, carry, action, frame, key, sample=False)
        discount = self.hp.gamma ** jnp.arange(self.config.horizon, dtype=jnp.float32)[:, None]
        objective = jnp.mean(jnp.sum(discount * traj["reward"], axis=0))
        return -objective, (jnp.zeros(()), {"imagined_return": objective})
