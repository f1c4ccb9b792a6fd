"""`imagination_ac` (alias `critic`): an actor-critic in the model's imagination, DreamerV3's
recipe for discrete actions.

From every real state of a replayed chunk the model imagines `horizon` steps, the buttons
drawn from Bernoulli(ã). A critic V(h) on the core's output learns the imagined λ-returns. The
actor learns by REINFORCE with the returns normalised by their 5-95 % range (at least 1), plus
an entropy bonus. The model never sees the controller's gradient, so it cannot predict more
reward to please it.

Where the model trains the look-ahead heads (`--lookahead-steps`), the imagined rewards are
the reward head's and the λ-returns end on the value head's value, which is fitted to real
λ-returns: the critic's targets then rest on real returns too.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from cdrl.learners.imagination import ImaginationLearner, imagine, lookahead_heads
from cdrl.learners.replay_base import button_entropy, button_log_prob, critic_value
from cdrl.training import lookahead
from cdrl.training.lookahead import lambda_returns


class ImaginationAC(ImaginationLearner):
    """See the module docstring. `model` is a controller variant that predicts reward."""

    name = "imagination_ac"

    def objective(self, params, critic, carry, action, frame, key):
        """(actor loss, (critic loss, terms)) of one imagined rollout from every start."""
        hp = self.hp
        traj = imagine(self.model, self.config.horizon, params, carry, action, frame, key, sample=True)
        h = jax.lax.stop_gradient(traj["h"])
        values = critic_value(critic, h)  # V after each imagined step
        rewards, ends = traj["reward"], values
        look = hp.model.lookahead
        heads = lookahead_heads(look, params)
        if heads is not None:  # the heads' reward, and their value after the last one at the end
            rewards = lookahead.reward(heads, h, look)
            ends = values.at[-1].set(lookahead.value_after(heads, h[-1], look))
        rets = jax.lax.stop_gradient(lambda_returns(rewards, ends, ends[-1], hp.gamma, hp.lam))
        h0 = jax.lax.stop_gradient(self.model.features(carry))
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
