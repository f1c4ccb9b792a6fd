"""The controller variants (thesis figures 3.4, 3.5 and 6.1).

The core's FC layer outputs a code for the next observation and, besides it, a code for the
next action (decoded by the controller D_a, the mirror of the action encoder) and, for the
reward variants, a code for the next reward (decoded by the reward head D_r):

- `action_loop` (3.4): input E_o(o_t) ++ E_a(a_t); outputs õ_{t+1} and ã_{t+1};
- `reward_prediction` (3.5): as 3.4, plus r̃_{t+1};
- `final_proposal` (6.1): closed loop − on observations (x_t = o_t − õ_t) ++ E_a(a_t);
  outputs õ_{t+1}, ã_{t+1}, r̃_{t+1}.

`a_t` is whatever the step's input carries: offline, the recorded action; online
(`cdrl.learners.thesis_ascent`), the model's own previous output ã_t (plus exploration noise), so that
gradients flow back through ã into D_a and E_a.
"""
from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp

from cdrl.models import nets
from cdrl.models.base import StepInput, bce_with_logits
from cdrl.models.observation import ClosedLoop, MainAction


def balanced_squared_error(pred: jax.Array, target: jax.Array, tol: float = 1e-6,
                           mask: jax.Array | None = None) -> jax.Array:
    """The squared error of `pred` averaged within each sign class of `target` (below -`tol`,
    within it, above it), the classes present in the batch weighing alike: a rare reward (a
    pellet eaten, a few steps in a hundred) counts as much as the common none. UNREAL's reward
    prediction (Jaderberg et al. 2016) balances so, sampling sequences that end in reward and in
    none equally often; the plain mean lets a frequent class decide what the core learns.
    `mask` (default: all) picks the entries that count."""
    mask = jnp.ones(target.shape, bool) if mask is None else jnp.broadcast_to(mask, target.shape)
    classes = [mask & (target < -tol), mask & (jnp.abs(target) <= tol), mask & (target > tol)]
    err = jnp.square(pred - target)
    per_class = [jnp.sum(jnp.where(m, err, 0.0)) / jnp.maximum(jnp.sum(m), 1) for m in classes]  # 0 if absent
    return sum(per_class) / sum(jnp.any(m).astype(jnp.float32) for m in classes)


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
        # The FC gain is for the decoder, whose SELU layers want unit-variance codes; the action
        # and reward codes feed small MLPs that it would only make stiff (at lr 1 with gain 5 the
        # reward head's squared error grows without bound within a few updates).
        cols = jnp.arange(sum(self.head_sizes())) < a.obs_code
        params["fc"]["dense0"]["kernel"] = params["fc"]["dense0"]["kernel"] * jnp.where(cols, 1.0, 1.0 / a.fc_init_gain)
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

    def _head_mask(self, params, head: int, group: str) -> dict:
        """1 on the FC layer's columns of code `head` (0: observation, 1: action, 2: reward) and
        on the parameters of `group`, 0 elsewhere (a pytree like `params`)."""
        sizes = self.head_sizes()
        cut = list(itertools.accumulate((0,) + sizes))
        cols = (jnp.arange(cut[-1]) >= cut[head]) & (jnp.arange(cut[-1]) < cut[head + 1])
        mask = jax.tree.map(jnp.zeros_like, params)
        fc = params["fc"]["dense0"]
        mask["fc"]["dense0"] = {"kernel": jnp.broadcast_to(cols, fc["kernel"].shape).astype(jnp.float32),
                                "bias": cols.astype(jnp.float32)}
        mask[group] = jax.tree.map(jnp.ones_like, params[group])
        return mask

    def controller_mask(self, params) -> dict:
        """1 where a parameter belongs to the controller, the map from the core's output h to
        ã: the FC layer's action-code columns and D_a; 0 elsewhere (a pytree like `params`).
        What the controller's own updates (imagination, actor-critic) may change."""
        return self._head_mask(params, 1, "act_dec")

    def reward_mask(self, params) -> dict:
        """1 on the reward head's own parameters (the FC layer's reward-code columns and D_r),
        0 elsewhere; for variants that predict reward."""
        return self._head_mask(params, 2, "reward_head")

    def features(self, carry) -> jax.Array:
        """h, the recurrent core's output, `[B, lstm_size]` (what the critic of an actor-critic reads)."""
        return carry.h

    def imagine_step(self, params, carry, frame, action):
        """One step of the model fed its own prediction `frame` (õ_t, `[B, H, W]`) and the
        action `action` (`[B, A]`): (carry, outputs with `logits`, the next predicted frame)."""
        carry, out = self.step(params, carry, StepInput(obs=frame, action=action,
                                                        is_first=jnp.zeros(action.shape[:1], bool)))
        return carry, out

    def default_loss_weights(self):
        weights = {"obs_bce": 1.0}
        if self.predicts_reward:
            weights["reward_mse"] = 1.0
            weights["reward_balanced"] = 0.0
        return weights

    def loss_terms(self, params, xs, outs, next_obs, next_reward):
        terms = {"obs_bce": bce_with_logits(outs["logits"], next_obs)}
        if self.predicts_reward:
            terms["reward_mse"] = jnp.mean(jnp.square(outs["reward"] - next_reward))
            terms["reward_balanced"] = balanced_squared_error(outs["reward"], next_reward)
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

    def features(self, carry) -> jax.Array:
        return carry["lstm"].h

    def imagine_step(self, params, carry, frame, action):
        """Fed its own prediction, closed loop − sees the error o_t − õ_t = 0 (the thesis's
        argument for it, section 6): the input code is E_o of a zero frame, the same for every
        step, so imagination needs neither the decoder nor the encoder. The outputs have no
        `logits` (the frame is not needed) and the carry's prediction is left as it was."""
        zero = jnp.zeros((1, self.arch.image_size, self.arch.image_size), jnp.float32)
        k_obs = nets.obs_encoder(params["obs_enc"], self.arch, zero)
        k = jnp.concatenate([jnp.broadcast_to(k_obs, (action.shape[0], k_obs.shape[-1])),
                             nets.mlp(params["act_enc"], action, final_selu=True)], axis=-1)
        lstm = nets.lstm_cell(params["lstm"], carry["lstm"], k)
        return {**carry, "lstm": lstm}, self.heads(params, self.fc(params, lstm.h))


CONTROLLER_VARIANTS = (ActionLoop, RewardPrediction, FinalProposal)
