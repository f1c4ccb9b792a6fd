"""The contract every model variant keeps, and the pieces variants share.

A variant is a frozen (hashable) object holding only the static `ArchConfig`; it is passed
to `jit` as a static argument. Its contract:

- `init(key) -> params`, `init_carry(batch) -> carry`;
- `step(params, carry, x_t) -> (carry, out_t)` with `x_t` a `StepInput` of one time step;
  episode resets are a mask inside the step (`x_t.is_first` selects the initial carry);
- `unroll(params, carry, xs) -> (carry, outs)` over time-major `[T, B, ...]` inputs: by
  default one `jax.lax.scan` of `step`; open-loop variants fuse it (encoder and decoder run
  over all T frames at once, only the recurrent core is scanned) and tests pin the fused
  path against the scan;
- `loss_terms(params, xs, outs, next_obs, next_reward) -> dict` of scalar terms, combined with a matching
  dict of weights (`default_loss_weights`), so that metrics-only terms carry weight 0.
"""
from __future__ import annotations

import dataclasses
import itertools
from typing import Any, ClassVar

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from cdrl.models import nets
from cdrl.models.arch import ArchConfig

Carry = Any
Outputs = dict

# Every combination of the three buttons (right, left, accelerate), pressed 1.0 or released 0.0.
BUTTON_COMBOS = np.asarray(list(itertools.product((0.0, 1.0), repeat=3)), np.float32)


@flax.struct.dataclass
class StepInput:
    """What the model sees at time t (each `[B, ...]`, or `[T, B, ...]` for an unroll)."""

    obs: jax.Array  # [B, H, W] float in [0, 1]
    action: jax.Array  # [B, action_dim] in [0, 1]; a_t, taken after seeing o_t
    is_first: jax.Array  # [B] bool: o_t starts a new episode, so the carry resets


def reset_where(is_first: jax.Array, initial: Carry, carry: Carry) -> Carry:
    """Per batch element, the initial carry where `is_first`, else the carried one."""

    def pick(init, cur):
        mask = is_first.reshape(is_first.shape + (1,) * (cur.ndim - 1))
        return jnp.where(mask, init, cur)

    return jax.tree.map(pick, initial, carry)


def elementwise_bce(logits: jax.Array, target: jax.Array) -> jax.Array:
    """Binary cross-entropy of sigmoid(logits) against `target` in [0, 1], element by element:
    -t log sigmoid(l) - (1 - t) log(1 - sigmoid(l)) = softplus(l) - t l. The one place the
    formula is written: `bce_with_logits` here and `cdrl.data.frames.pixel_bce` average it."""
    return jax.nn.softplus(logits) - target * logits


def bce_with_logits(logits: jax.Array, target: jax.Array) -> jax.Array:
    """Binary cross-entropy of sigmoid(logits) against `target` in [0, 1], averaged."""
    return jnp.mean(elementwise_bce(logits, target))


# Frames per pass of the observation encoder over a chunk, where its image-sized layers are
# large (`nets.recomputes_image_layers`): a chunk of more frames is encoded in passes of this
# many, one after the other (`lax.map`), so that the backward pass's working arrays of those
# layers are those of one pass. Thesis preset, B 8 x T 32 (256 frames): 809 MiB of XLA scratch
# for the train step instead of 916 MiB in one pass, frames per second unchanged
# (`benchmarks/train_throughput.py`).
ENCODER_PASS_FRAMES = 128


def _flat(fn, x: jax.Array, n_trailing: int, pass_frames: int | None = None) -> jax.Array:
    """Apply a `[N, ...] -> [N, ...]` network to an array with any leading dims; with
    `pass_frames`, over at most that many of the N at a time (the same values)."""
    lead = x.shape[: x.ndim - n_trailing]
    flat = x.reshape((-1,) + x.shape[x.ndim - n_trailing:])
    n = flat.shape[0]
    if pass_frames is None or n <= pass_frames:
        y = fn(flat)
    else:
        whole = n - n % pass_frames
        passes = jax.lax.map(fn, flat[:whole].reshape((whole // pass_frames, pass_frames) + flat.shape[1:]))
        y = passes.reshape((whole,) + passes.shape[2:])
        if whole < n:
            y = jnp.concatenate([y, fn(flat[whole:])])
    return y.reshape(lead + y.shape[1:])


@dataclasses.dataclass(frozen=True)
class Variant:
    """Base class: see the module docstring for the contract."""

    arch: ArchConfig
    name: ClassVar[str] = ""
    uses_action: ClassVar[bool] = False
    # Variants whose predicted code lives in the input code's space (thesis figure 5.6).
    shared_code_space: ClassVar[bool] = False
    # Variants with a controller D_a; `cdrl train` trains them online against the game.
    has_controller: ClassVar[bool] = False
    # The parameter groups of the controller (what a reward ascent of scope "controller" changes).
    controller_groups: ClassVar[tuple[str, ...]] = ()
    # Variants with a reward head D_r: their outputs carry `reward`, r̃_{t+1}.
    predicts_reward: ClassVar[bool] = False
    # Variants trained in stages of loss weights (`stage_loss_weights`), one after another.
    stages: ClassVar[bool] = False

    # ---- parameters and carries
    def init(self, key: jax.Array) -> dict:
        raise NotImplementedError

    def init_carry(self, batch: int) -> Carry:
        raise NotImplementedError

    def core_in_size(self) -> int:
        return self.arch.obs_code + (self.arch.action_code if self.uses_action else 0)

    def _init_common(self, key: jax.Array, recurrent: bool = True) -> dict:
        a = self.arch
        k = jax.random.split(key, 5)
        params = {
            "obs_enc": nets.init_obs_encoder(k[0], a),
            "obs_dec": nets.init_obs_decoder(k[1], a),
        }
        if recurrent:
            params["lstm"] = nets.init_lstm(k[2], self.core_in_size(), a.lstm_size)
            params["fc"] = self._init_core_fc(k[3], a.obs_code)
        else:
            params["fc"] = nets.init_mlp(k[3], (self.core_in_size(), a.obs_code), final_selu=True)
        if self.uses_action:
            params["act_enc"] = nets.init_mlp(
                k[4], (a.action_dim, *a.action_hidden, a.action_code), final_selu=True
            )
        return params

    def _init_core_fc(self, key: jax.Array, n_out: int) -> dict:
        """The FC layer reading the LSTM's output h: LeCun-normal times `arch.fc_init_gain`.
        With Glorot weights and zero biases the LSTM's gates start near 0.5, so h has a
        fraction of its input's spread; the gain gives the SELU layers after it back the
        unit-variance input they assume."""
        fc = nets.init_mlp(key, (self.arch.lstm_size, n_out), final_selu=True)
        fc["dense0"]["kernel"] = fc["dense0"]["kernel"] * self.arch.fc_init_gain
        return fc

    # ---- time
    def step(self, params: dict, carry: Carry, x: StepInput) -> tuple[Carry, Outputs]:
        raise NotImplementedError

    def unroll(self, params: dict, carry: Carry, xs: StepInput) -> tuple[Carry, Outputs]:
        return jax.lax.scan(lambda c, x: self.step(params, c, x), carry, xs)

    def unroll_states(self, params: dict, carry: Carry, xs: StepInput) -> tuple[Carry, Outputs, Carry]:
        """`unroll`, with the carry after every step (`[T, B, ...]`) as well."""
        def body(c, x):
            c, out = self.step(params, c, x)
            return c, (out, c)

        carry, (outs, carries) = jax.lax.scan(body, carry, xs)
        return carry, outs, carries

    def unroll_fed(self, params: dict, carry: Carry, xs: StepInput, observed: jax.Array) -> tuple[Carry, Outputs]:
        """`unroll` where step t sees the real frame `xs.obs[t]` only where `observed` `[T, B]`
        is true, and elsewhere the sigmoid of its own previous prediction, which keeps its
        gradient (back-propagation through the model's own predictions, as Oh et al. 2015
        train for many steps). The actions are always `xs.action`. Step 0 must be observed."""
        def body(state, x):
            carry, prev = state
            x, seen = x
            obs = jnp.where(seen[:, None, None], x.obs, jax.nn.sigmoid(prev))
            carry, out = self.step(params, carry, x.replace(obs=obs))
            return (carry, out["logits"]), out

        (carry, _), outs = jax.lax.scan(body, (carry, jnp.zeros_like(xs.obs[0])), (xs, observed))
        return carry, outs

    # ---- losses
    def stage_loss_weights(self) -> tuple[dict[str, float], ...]:
        """The loss weights of each training stage, for variants with `stages`."""
        raise NotImplementedError

    def default_loss_weights(self) -> dict[str, float]:
        weights = {"obs_bce": 1.0}
        if self.shared_code_space:
            weights["code_pred_mse"] = 0.0
        return weights

    def loss_terms(
        self, params: dict, xs: StepInput, outs: Outputs, next_obs: jax.Array, next_reward: jax.Array
    ) -> dict:
        terms = {"obs_bce": bce_with_logits(outs["logits"], next_obs)}
        if self.shared_code_space:
            terms["code_pred_mse"] = code_prediction_error(outs, xs.is_first)
        return terms

    # ---- shared pieces
    def encode(self, params: dict, obs: jax.Array, action: jax.Array) -> jax.Array:
        """Input code k_t for frames `[..., H, W]` (and actions `[..., A]`)."""
        passes = ENCODER_PASS_FRAMES if nets.recomputes_image_layers(self.arch) else None
        k = _flat(lambda o: nets.obs_encoder(params["obs_enc"], self.arch, o), obs, 2, passes)
        if self.uses_action:
            ka = nets.mlp(params["act_enc"], action, final_selu=True)
            k = jnp.concatenate([k, ka], axis=-1)
        return k

    def decode(self, params: dict, code: jax.Array) -> jax.Array:
        """Logits of the predicted frame for codes `[..., obs_code]`."""
        return _flat(lambda d: nets.obs_decoder_logits(params["obs_dec"], self.arch, d), code, 1)

    def fc(self, params: dict, h: jax.Array) -> jax.Array:
        return nets.mlp(params["fc"], h, final_selu=True)

    def _outputs(self, params: dict, k: jax.Array, d: jax.Array) -> Outputs:
        """Read out the core's output code `d` (input code `k` kept for the metrics)."""
        return {"logits": self.decode(params, d), "code": k, "pred_code": d}


def code_prediction_errors(outs: Outputs) -> jax.Array:
    """Per step `[T - 1, B]`: MSE(d_{t+1}, k_{t+1}) over the code's values, for steps 0 .. T - 2
    of a chunk's outputs (the predicted code against the next step's input code)."""
    pred, code = outs["pred_code"][:-1], outs["code"][1:, ..., : outs["pred_code"].shape[-1]]
    return jnp.mean(jnp.square(pred - code), axis=-1)


def code_prediction_error(outs: Outputs, is_first: jax.Array) -> jax.Array:
    """MSE(d_{t+1}, k_{t+1}) over the pairs inside the chunk that do not cross an episode start."""
    valid = (~is_first[1:]).astype(jnp.float32)
    return jnp.sum(code_prediction_errors(outs) * valid) / jnp.maximum(jnp.sum(valid), 1.0)


