"""`imagined_ascent` (alias `imagine`): the thesis's ascent in the model's imagination.

From every real state of a replayed chunk the model imagines `horizon` steps, fed its own
predictions and the controller's actions ã as they are (deterministic). The controller ascends
the discounted predicted reward of those steps, its gradient taken through the model. Where the
model trains the look-ahead heads (`--lookahead-steps`), their reward scores the steps and their
value, fitted to real λ-returns, is added at the end (`imagined_return`).
"""
from __future__ import annotations

import jax.numpy as jnp

from cdrl.learners.imagination import ImaginationLearner, imagine, imagined_return


class ImaginedAscent(ImaginationLearner):
    """See the module docstring. `model` is a controller variant that predicts reward."""

    name = "imagined_ascent"

    def objective(self, params, critic, carry, action, frame, key):
        """Minus the mean imagined return (the controller's loss); no critic."""
        traj = imagine(self.model, self.config.horizon, params, carry, action, frame, key, sample=False)
        objective = jnp.mean(imagined_return(self.hp.model.lookahead, params, traj["reward"], traj["h"],
                                             self.hp.gamma))
        return -objective, (jnp.zeros(()), {"imagined_return": objective})
