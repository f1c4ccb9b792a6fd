"""The networks of the thesis (section 4.3.1) as pure functions over parameter pytrees.

Every network is a pair `init_*(key, ...) -> params` and `apply(params, ..., x) -> y`.
Parameters are nested dicts of arrays (one leaf per kernel and per bias, the thesis's
"independently initialised parameter groups"); static sizes come from `ArchConfig`.
Images are NHWC inside the networks; the public encode/decode functions take and return
`[B, H, W]` frames. Initialisation: LeCun-normal for layers followed by SELU, Glorot for
the rest (LSTM, the sigmoid output layers, linear heads). The convolutions are
`cdrl.models.conv`'s.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from cdrl.models.arch import ArchConfig
from cdrl.models.conv import conv2d, conv2d_selu, conv_transpose, conv_transpose_selu, formulation  # noqa: F401 (nets.conv2d: the API)

Params = dict

_lecun = jax.nn.initializers.lecun_normal()
_glorot = jax.nn.initializers.glorot_uniform()


def _dense_init(key, n_in: int, n_out: int, selu: bool) -> Params:
    init = _lecun if selu else _glorot
    return {"kernel": init(key, (n_in, n_out), jnp.float32), "bias": jnp.zeros((n_out,), jnp.float32)}


def dense(params: Params, x: jax.Array) -> jax.Array:
    return x @ params["kernel"] + params["bias"]


# --------------------------------------------------------------------------- MLPs


def init_mlp(key, sizes: tuple[int, ...], final_selu: bool) -> Params:
    """An MLP with layer widths `sizes` (input first); SELU after every hidden layer."""
    keys = jax.random.split(key, len(sizes) - 1)
    n = len(sizes) - 1
    return {
        f"dense{i}": _dense_init(keys[i], sizes[i], sizes[i + 1], selu=(i < n - 1) or final_selu)
        for i in range(n)
    }


def mlp(params: Params, x: jax.Array, final_selu: bool) -> jax.Array:
    n = len(params)
    for i in range(n):
        x = dense(params[f"dense{i}"], x)
        if i < n - 1 or final_selu:
            x = jax.nn.selu(x)
    return x


# --------------------------------------------------------------------------- convolutions


def init_obs_encoder(key, arch: ArchConfig) -> Params:
    keys = jax.random.split(key, len(arch.encoder))
    params, in_ch = {}, 1
    for i, spec in enumerate(arch.encoder):
        shape = (spec.kernel, spec.kernel, in_ch, spec.features)
        params[f"conv{i}"] = {
            "kernel": _lecun(keys[i], shape, jnp.float32),
            "bias": jnp.zeros((spec.features,), jnp.float32),
        }
        in_ch = spec.features
    return params


def _conv_selu(x: jax.Array, kernel: jax.Array, bias: jax.Array, stride: int, padding: int,
               backend: str = "auto") -> jax.Array:
    return conv2d_selu(x, kernel, bias, stride, padding, backend)


def _conv_transpose_selu(x: jax.Array, kernel: jax.Array, bias: jax.Array, stride: int, padding: int,
                         backend: str = "auto") -> jax.Array:
    return conv_transpose_selu(x, kernel, bias, stride, padding, backend)


# The layers next to the image (the first encoder layer, the last hidden decoder layer) have
# the largest outputs: 76 x 76 x 16 per frame at the thesis's size, 95 MB over a chunk of 256
# frames. Differentiated as they are, each keeps its pre-activation beside its output until
# the backward pass; recomputed there from their inputs instead (one convolution each), the
# thesis-sized train step at B 8 x T 32 needs 916 MiB of XLA scratch instead of 1029 MiB
# (`closed_loop_minus`: 593 instead of 863 MiB with the encoder's passes), at no measurable
# cost in speed (`benchmarks/train_throughput.py`). Where that output is small, the
# recomputation is all cost (the small preset's 32 x 32 x 8, 32 KiB a frame: online programs
# 3-5 % slower), so only from RECOMPUTE_FROM_BYTES a frame.
RECOMPUTE_FROM_BYTES = 128 * 1024
_conv_selu_recomputed = jax.checkpoint(_conv_selu, static_argnums=(3, 4, 5))
_conv_transpose_selu_recomputed = jax.checkpoint(_conv_transpose_selu, static_argnums=(3, 4, 5))


def recomputes_image_layers(arch: ArchConfig) -> bool:
    """Whether the layers next to the image are recomputed in the backward pass: their output,
    `image_size / stride` squared times the first layer's features in float32, is at least
    RECOMPUTE_FROM_BYTES a frame (the thesis preset: yes; small and tiny: no). Not on oneDNN:
    its layers keep only their output, from which the backward reads SELU's derivative."""
    if formulation(arch.conv) == "onednn":
        return False
    return arch.encoder_sizes[1] ** 2 * arch.encoder[0].features * 4 >= RECOMPUTE_FROM_BYTES


def obs_encoder(params: Params, arch: ArchConfig, frames: jax.Array) -> jax.Array:
    """E_o: frames `[B, H, W]` in [0, 1] -> codes `[B, obs_code]` (SELU after every layer).
    The frames enter as (frames - arch.obs_mean) / arch.obs_std."""
    x = (frames[..., None] - arch.obs_mean) / arch.obs_std
    recompute = recomputes_image_layers(arch)
    for i, spec in enumerate(arch.encoder):
        layer = params[f"conv{i}"]
        f = _conv_selu_recomputed if i == 0 and recompute else _conv_selu
        x = f(x, layer["kernel"], layer["bias"], spec.stride, spec.padding, arch.conv)
    return x.reshape(x.shape[0], -1)


def _decoder_layers(arch: ArchConfig):
    """(spec, in_channels, out_channels) of each decoder layer, first layer first."""
    chans = [1] + [s.features for s in arch.encoder]
    specs = list(reversed(arch.encoder))
    return [(spec, chans[-1 - i], chans[-2 - i]) for i, spec in enumerate(specs)]


def init_obs_decoder(key, arch: ArchConfig) -> Params:
    layers = _decoder_layers(arch)
    keys = jax.random.split(key, len(layers))
    params = {}
    for i, (spec, c_in, c_out) in enumerate(layers):
        init = _glorot if i == len(layers) - 1 else _lecun
        params[f"deconv{i}"] = {
            # [kh, kw, in, out]: kernel[y, x, i, o] is PyTorch's ConvTranspose2d weight[i, o, y, x].
            "kernel": init(keys[i], (spec.kernel, spec.kernel, c_in, c_out), jnp.float32),
            "bias": jnp.zeros((c_out,), jnp.float32),
        }
    return params


def obs_decoder_logits(params: Params, arch: ArchConfig, codes: jax.Array) -> jax.Array:
    """D_o before its output sigmoid: codes `[B, obs_code]` -> logits `[B, H, W]`."""
    layers = _decoder_layers(arch)
    x = codes.reshape(codes.shape[0], 1, 1, codes.shape[-1])
    last, recompute = len(layers) - 1, recomputes_image_layers(arch)
    for i, (spec, _, _) in enumerate(layers):
        layer = params[f"deconv{i}"]
        if i == last:
            x = conv_transpose(x, layer["kernel"], spec.stride, spec.padding, arch.conv) + layer["bias"]
        else:
            f = _conv_transpose_selu_recomputed if i == last - 1 and recompute else _conv_transpose_selu
            x = f(x, layer["kernel"], layer["bias"], spec.stride, spec.padding, arch.conv)
    return x[..., 0]


# --------------------------------------------------------------------------- LSTM


class LSTMState(NamedTuple):
    """The recurrent state: output `h` and error carousel `c`, each `[B, lstm_size]`."""

    h: jax.Array
    c: jax.Array


def init_lstm(key, n_in: int, n_hidden: int) -> Params:
    """Gate order along the last axis: forget, input, output, update (thesis eq. 3.4)."""
    k1, k2 = jax.random.split(key)
    return {
        "w_input": _glorot(k1, (n_in, 4 * n_hidden), jnp.float32),
        "w_recurrent": _glorot(k2, (n_hidden, 4 * n_hidden), jnp.float32),
        "bias": jnp.zeros((4 * n_hidden,), jnp.float32),
    }


def lstm_zeros(batch: int, n_hidden: int) -> LSTMState:
    return LSTMState(jnp.zeros((batch, n_hidden), jnp.float32), jnp.zeros((batch, n_hidden), jnp.float32))


def lstm_cell(params: Params, state: LSTMState, x: jax.Array) -> LSTMState:
    """One LSTM step (thesis eq. 3.4) on inputs `x` `[B, n_in]`."""
    return _gates(x @ params["w_input"] + state.h @ params["w_recurrent"] + params["bias"], state.c)


def _gates(z: jax.Array, c_prev: jax.Array) -> LSTMState:
    """The LSTM's state from its gates' pre-activations `z` `[B, 4 n_hidden]` and the carousel before."""
    f, i, o, u = jnp.split(z, 4, axis=-1)
    c = jax.nn.sigmoid(f) * c_prev + jax.nn.sigmoid(i) * jnp.tanh(u)
    return LSTMState(jax.nn.sigmoid(o) * jnp.tanh(c), c)


def lstm_unroll(params: Params, state: LSTMState, xs: jax.Array, is_first: jax.Array,
                unroll: int = 1) -> tuple[LSTMState, LSTMState]:
    """`lstm_cell` over time-major inputs `xs` `[T, B, n_in]`, the state reset to zeros where
    `is_first` `[T, B]`: (final state, every step's state `[T, B, n_hidden]` each).

    The input product of all T steps is one matrix product before the scan; only the recurrent
    product is scanned. Inside the scan the recurrent kernel's gradient is not summed step by
    step: the backward pass returns every step's gate gradients, and the kernel's gradient is
    one product after it (`_recurrent_scan`). The same values as the scan of `lstm_cell` (tested).
    """
    z_in = xs @ params["w_input"] + params["bias"]
    return _recurrent_scan(params["w_recurrent"], z_in, state, is_first, unroll)


def _recurrent_steps(w_recurrent, z_in, state, is_first, unroll):
    """The scan of `lstm_unroll` for gate inputs `z_in` = x W_input + bias: ((final state,
    states), the state each step starts from, after its reset)."""
    def body(carry: LSTMState, inp):
        z_t, first = inp
        reset = first[:, None]
        h_prev, c_prev = jnp.where(reset, 0.0, carry.h), jnp.where(reset, 0.0, carry.c)
        state = _gates(z_t + h_prev @ w_recurrent, c_prev)
        return state, (state, h_prev)

    final, (states, h_prevs) = jax.lax.scan(body, state, (z_in, is_first), unroll=unroll)
    return (final, states), h_prevs


@functools.partial(jax.custom_vjp, nondiff_argnums=(4,))
def _recurrent_scan(w_recurrent, z_in, state, is_first, unroll):
    return _recurrent_steps(w_recurrent, z_in, state, is_first, unroll)[0]


def _recurrent_scan_fwd(w_recurrent, z_in, state, is_first, unroll):
    # The backward scan sees the kernel as a constant: it carries no kernel gradient.
    out, pullback, h_prevs = jax.vjp(lambda z, s: _recurrent_steps(w_recurrent, z, s, is_first, unroll),
                                     z_in, state, has_aux=True)
    return out, (pullback, h_prevs)


def _recurrent_scan_bwd(unroll, residuals, cotangent):
    pullback, h_prevs = residuals
    d_z, d_state = pullback(cotangent)
    # The gates' pre-activation at step t is z_in[t] + h_prev[t] W: its gradient is d_z[t], and
    # W's is the sum over steps of h_prev[t]^T d_z[t], one product over all T x B rows.
    d_w = jnp.einsum("tbi,tbo->io", h_prevs, d_z)
    return d_w, d_z, d_state, None


_recurrent_scan.defvjp(_recurrent_scan_fwd, _recurrent_scan_bwd)
