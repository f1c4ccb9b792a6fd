"""The thesis's observation-predicting variants (chapter 4; figures 3.2, 3.3, 4.2-4.7), each a pure step
function scanned over time: baseline_ff, baseline_recurrent, main, main_action, residual,
residual_error, closed_loop_plus, closed_loop_minus. The controller variants are in
`cdrl.models.controller`; the registry of both is `cdrl.models.VARIANTS`.
"""
from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp

from cdrl.models import nets
from cdrl.models.base import Carry, Variant, bce_with_logits, reset_where

# Steps of the recurrent core per iteration of its scan: XLA's CPU loops cost a fixed
# overhead per iteration, which matters for the small per-step matmuls of one batch
# (thesis preset, B 1, T 32: the LSTM's forward and backward 13.6 ms unrolled 1, 9.9 ms unrolled 8).
CORE_UNROLL = 8


class OpenLoop(Variant):
    """Variants whose input does not depend on their own predictions.

    `step` is encode -> recur -> decode; `unroll` runs the encoder and decoder over all T
    frames at once and runs only the recurrent core step by step (`core`).
    """

    def recur(self, params: dict, carry: Carry, k: jax.Array, is_first: jax.Array):
        raise NotImplementedError

    def core(self, params: dict, carry: Carry, ks: jax.Array, is_first: jax.Array):
        """The recurrent core over all T codes `ks`: (carry, codes d, the carry after every
        step). By default a scan of `recur`."""
        def body(c, kx):
            c, d = self.recur(params, c, kx[0], kx[1])
            return c, (d, c)

        carry, (ds, carries) = jax.lax.scan(body, carry, (ks, is_first), unroll=CORE_UNROLL)
        return carry, ds, carries

    def step(self, params, carry, x):
        k = self.encode(params, x.obs, x.action)
        carry, d = self.recur(params, carry, k, x.is_first)
        return carry, self._outputs(params, k, d)

    def unroll(self, params, carry, xs):
        carry, outs, _ = self.unroll_states(params, carry, xs)
        return carry, outs

    def unroll_states(self, params, carry, xs):
        ks = self.encode(params, xs.obs, xs.action)
        carry, ds, carries = self.core(params, carry, ks, xs.is_first)
        return carry, self._outputs(params, ks, ds), carries


class BaselineFF(OpenLoop):
    """Figure 4.2: k_t = E_o(o_t); d = FC(k_t); prediction D_o(d). No recurrence."""

    name = "baseline_ff"

    def init(self, key):
        return self._init_common(key, recurrent=False)

    def init_carry(self, batch):
        return ()

    def recur(self, params, carry, k, is_first):
        return carry, self.fc(params, k)


class Main(OpenLoop):
    """Figure 3.2: k_t = E_o(o_t); h_t = LSTM(k_t); d_{t+1} = FC(h_t); prediction D_o(d_{t+1}).

    Over a chunk only the LSTM's recurrent product runs step by step (`nets.lstm_unroll`);
    its input product and the FC layer run over all T steps at once.
    """

    name = "main"

    def init(self, key):
        return self._init_common(key)

    def init_carry(self, batch):
        return nets.lstm_zeros(batch, self.arch.lstm_size)

    def core_input(self, k: jax.Array) -> jax.Array:
        """What the LSTM reads of the input code k."""
        return k

    def readout(self, params: dict, k: jax.Array, h: jax.Array) -> jax.Array:
        """The core's output code d_{t+1} from the input code k_t and the LSTM's output h_t."""
        return self.fc(params, h)

    def recur(self, params, carry, k, is_first):
        carry = reset_where(is_first, self.init_carry(k.shape[0]), carry)
        carry = nets.lstm_cell(params["lstm"], carry, self.core_input(k))
        return carry, self.readout(params, k, carry.h)

    def core(self, params, carry, ks, is_first):
        carry, states = nets.lstm_unroll(params["lstm"], carry, self.core_input(ks), is_first, CORE_UNROLL)
        return carry, self.readout(params, ks, states.h), states


class MainAction(Main):
    """Figure 3.3: as main, with k_t = E_o(o_t) ++ E_a(a_t)."""

    name = "main_action"
    uses_action = True


class Residual(Main):
    """Figure 4.4: d_{t+1} = k_t + FC(LSTM(k_t))."""

    name = "residual"
    shared_code_space = True

    def readout(self, params, k, h):
        return k + self.fc(params, h)


class ResidualError(Main):
    """Figure 4.5: e_t = k_t - d_t (d_0 = 0); d_{t+1} = k_t + FC(LSTM(e_t))."""

    name = "residual_error"
    shared_code_space = True

    # The LSTM reads the carried prediction: a scan of `recur`, step by step.
    core = OpenLoop.core

    def init_carry(self, batch):
        return {"lstm": super().init_carry(batch), "pred_code": jnp.zeros((batch, self.arch.obs_code))}

    def recur(self, params, carry, k, is_first):
        carry = reset_where(is_first, self.init_carry(k.shape[0]), carry)
        lstm = nets.lstm_cell(params["lstm"], carry["lstm"], k - carry["pred_code"])
        d = k + self.fc(params, lstm.h)
        return {"lstm": lstm, "pred_code": d}, d


class BaselineRecurrent(Main):
    """Figure 4.3, two stages sharing one program: an autoencoder D_o(E_o(o_t)) trained on
    reconstruction ('recon_bce'), and an LSTM+FC trained on the frozen codes with MSE
    ('code_mse'). The stages are loss-weight settings (`stage_loss_weights`); 'obs_bce',
    BCE(D_o(d_{t+1}), o_{t+1}), is the comparable evaluation metric (weight 0)."""

    name = "baseline_recurrent"
    shared_code_space = True
    stages = True

    def core_input(self, k):
        return jax.lax.stop_gradient(k)

    def _outputs(self, params, k, d):
        out = super()._outputs(params, k, d)
        out["recon_logits"] = self.decode(params, k)
        return out

    def default_loss_weights(self):
        return self.stage_loss_weights()[0]

    def stage_loss_weights(self) -> tuple[dict[str, float], ...]:
        """Stage 1 trains the autoencoder, stage 2 the LSTM+FC on its frozen codes."""
        base = {"obs_bce": 0.0, "code_pred_mse": 0.0}
        return (
            {**base, "recon_bce": 1.0, "code_mse": 0.0},
            {**base, "recon_bce": 0.0, "code_mse": 1.0},
        )

    def loss_terms(self, params, xs, outs, next_obs, next_reward):
        terms = super().loss_terms(params, xs, outs, next_obs, next_reward)
        terms["recon_bce"] = bce_with_logits(outs["recon_logits"], xs.obs)
        target = jax.lax.stop_gradient(self.encode(params, next_obs, None))
        terms["code_mse"] = jnp.mean(jnp.square(outs["pred_code"] - target))
        return terms


class ClosedLoop(Variant):
    """Figures 4.6 / 4.7: the input is o_t + sign * õ_t (õ_0 = 0), then the main model.

    The fed-back prediction õ_t keeps its gradient (no stop-gradient): errors flow back
    through it into the previous step's decoder, core and encoder.
    """

    sign: ClassVar[float] = 1.0

    def init(self, key):
        return self._init_common(key)

    def init_carry(self, batch):
        size = self.arch.image_size
        return {
            "lstm": nets.lstm_zeros(batch, self.arch.lstm_size),
            "pred_obs": jnp.zeros((batch, size, size), jnp.float32),
        }

    def step(self, params, carry, x):
        carry = reset_where(x.is_first, self.init_carry(x.obs.shape[0]), carry)
        k = self.encode(params, x.obs + self.sign * carry["pred_obs"], x.action)
        lstm = nets.lstm_cell(params["lstm"], carry["lstm"], k)
        out = self._outputs(params, k, self.fc(params, lstm.h))
        return {"lstm": lstm, "pred_obs": jax.nn.sigmoid(out["logits"])}, out


class ClosedLoopPlus(ClosedLoop):
    name = "closed_loop_plus"
    sign = 1.0


class ClosedLoopMinus(ClosedLoop):
    name = "closed_loop_minus"
    sign = -1.0


OBSERVATION_VARIANTS = (BaselineFF, BaselineRecurrent, Main, MainAction, Residual, ResidualError,
                        ClosedLoopPlus, ClosedLoopMinus)
