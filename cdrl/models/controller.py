"""The controller variants (thesis figures 3.4, 3.5 and 6.1).

The core's FC layer outputs a code for the next observation and, besides it, a code for the
next action (decoded by the controller D_a, the mirror of the action encoder) and, for the
reward variants, a code for the next reward (decoded by the reward head D_r):

- `action_loop` (3.4): input E_o(o_t) ++ E_a(a_t); outputs õ_{t+1} and ã_{t+1};
- `reward_prediction` (3.5): as 3.4, plus r̃_{t+1};
- `final_proposal` (6.1): closed loop − on observations (x_t = o_t − õ_t) ++ E_a(a_t);
  outputs õ_{t+1}, ã_{t+1}, r̃_{t+1}.

`a_t` is whatever the step's input carries: offline, the recorded action; online
(`cdrl.training.online`), the model's own previous output ã_t (plus exploration noise), so that
gradients flow back through ã into D_a and E_a.
"""
from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp

from cdrl.models import nets
from cdrl.models.base import bce_with_logits
from cdrl.models.observation import ClosedLoop, MainAction


class _Heads:
    """Mixin: split the FC output into observation / action / reward codes and decode them."""

    has_controller = True
    controller_groups = ("act_dec",)

    def head_sizes(self) -> tuple[int, ...]:
        a = self.arch
        return (a.obs_code, a.action_code) + ((a.reward_code,) if self.predicts_reward else ())

    def init(self, key):
        a = self.arch
        k_base, k_fc, k_act, k_rew = jax.random.split(key, 4)
        params = self._init_common(k_base)
        params["fc"] = self._init_core_fc(k_fc, sum(self.head_sizes()))
        params["act_dec"] = nets.init_mlp(
            k_act, (a.action_code, *reversed(a.action_hidden), a.action_dim), final_selu=False
        )
        if self.predicts_reward:
            params["reward_head"] = nets.init_mlp(k_rew, (a.reward_code, a.reward_hidden, 1), final_selu=False)
        return params

    def heads(self, params, d_all) -> dict:
        """Decode the FC output: `pred_code` (observation part), `action` ã, `reward` r̃."""
        cuts = list(itertools.accumulate(self.head_sizes()))[:-1]
        parts = jnp.split(d_all, cuts, axis=-1)
        out = {
            "pred_code": parts[0],
            "action": jax.nn.sigmoid(nets.mlp(params["act_dec"], parts[1], final_selu=False)),
        }
        if self.predicts_reward:
            out["reward"] = nets.mlp(params["reward_head"], parts[2], final_selu=False)[..., 0]
        return out

    def default_loss_weights(self):
        weights = {"obs_bce": 1.0}
        if self.predicts_reward:
            weights["reward_mse"] = 1.0
        return weights

    def loss_terms(self, params, xs, outs, next_obs, next_reward):
        terms = {"obs_bce": bce_with_logits(outs["logits"], next_obs)}
        if self.predicts_reward:
            terms["reward_mse"] = jnp.mean(jnp.square(outs["reward"] - next_reward))
        return terms

    def _outputs(self, params, k, d_all):
        out = self.heads(params, d_all)
        return {**out, "logits": self.decode(params, out["pred_code"]), "code": k}


class ActionLoop(_Heads, MainAction):
    """Figure 3.4: actions enter as inputs and are generated as self-fulfilling predictions."""

    name = "action_loop"


class RewardPrediction(ActionLoop):
    """Figure 3.5: the action loop plus a predicted reward r̃_{t+1} (rewards are not an input)."""

    name = "reward_prediction"
    predicts_reward = True


class FinalProposal(_Heads, ClosedLoop):
    """Figure 6.1: closed loop − on observations, the action loop and the reward head."""

    name = "final_proposal"
    uses_action = True
    predicts_reward = True
    sign = -1.0


CONTROLLER_VARIANTS = (ActionLoop, RewardPrediction, FinalProposal)
