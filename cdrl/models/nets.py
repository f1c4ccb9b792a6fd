"""The networks of the thesis (section 4.3.1) as pure functions over parameter pytrees.

Every network is a pair `init_*(key, ...) -> params` and `apply(params, ..., x) -> y`.
Parameters are nested dicts of arrays (one leaf per kernel and per bias, the thesis's
"independently initialised parameter groups"); static sizes come from `ArchConfig`.
Images are NHWC inside the networks; the public encode/decode functions take and return
`[B, H, W]` frames. Initialisation: LeCun-normal for layers followed by SELU, Glorot for
the rest (LSTM, the sigmoid output layers, linear heads).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from cdrl.models.arch import ArchConfig

Params = dict

_lecun = jax.nn.initializers.lecun_normal()
_glorot = jax.nn.initializers.glorot_uniform()
_DIMS = ("NHWC", "HWIO", "NHWC")


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


def space_to_depth(x: jax.Array, s: int) -> jax.Array:
    """[N, H, W, C] -> [N, H/s, W/s, s*s*C], channels ordered (row phase, column phase, C)."""
    n, h, w, c = x.shape
    x = x.reshape(n, h // s, s, w // s, s, c).transpose(0, 1, 3, 2, 4, 5)
    return x.reshape(n, h // s, w // s, s * s * c)


def conv2d(x: jax.Array, kernel: jax.Array, stride: int, padding: int) -> jax.Array:
    """Strided convolution (NHWC, HWIO kernel, symmetric zero padding) as one matrix multiply.

    Where the stride divides the kernel (every layer of the presets), the padded input is
    folded space-to-depth by the stride, which turns the convolution into a stride-1 one with
    a (k/s)^2 window: its patches are (k/s)^2 unstrided shifts, concatenated and multiplied
    by the re-ordered kernel. On XLA's CPU backend this and its gradient (pads, slices and
    matrix multiplies) run faster than the native convolution, whose input and kernel
    gradients take slow dilated paths. Other strides use `jax.lax.conv_general_dilated`.
    """
    k, _, c_in, c_out = kernel.shape
    if k % stride:
        return jax.lax.conv_general_dilated(
            x, kernel, (stride, stride), [(padding, padding)] * 2, dimension_numbers=_DIMS
        )
    n, h, w, _ = x.shape
    q = k // stride
    h_out, w_out = (h + 2 * padding - k) // stride + 1, (w + 2 * padding - k) // stride + 1
    # Pad, then crop or extend to exactly (out - 1 + q) * stride rows and columns.
    rows, cols = (h_out - 1 + q) * stride, (w_out - 1 + q) * stride
    x = jnp.pad(x, ((0, 0), (padding, max(0, rows - h - padding)), (padding, max(0, cols - w - padding)), (0, 0)))
    x = space_to_depth(x[:, :rows, :cols], stride)
    patches = jnp.concatenate(
        [x[:, qy: qy + h_out, qx: qx + w_out] for qy in range(q) for qx in range(q)], axis=-1
    )
    # kernel[qy*s + ry, qx*s + rx, c, o] -> rows ordered (qy, qx, ry, rx, c) like the patches.
    kernel = kernel.reshape(q, stride, q, stride, c_in, c_out).transpose(0, 2, 1, 3, 4, 5)
    y = patches.reshape(-1, k * k * c_in) @ kernel.reshape(k * k * c_in, c_out)
    return y.reshape(n, h_out, w_out, c_out)


def obs_encoder(params: Params, arch: ArchConfig, frames: jax.Array) -> jax.Array:
    """E_o: frames `[B, H, W]` in [0, 1] -> codes `[B, obs_code]` (SELU after every layer).
    The frames enter as (frames - arch.obs_mean) / arch.obs_std."""
    x = (frames[..., None] - arch.obs_mean) / arch.obs_std
    for i, spec in enumerate(arch.encoder):
        layer = params[f"conv{i}"]
        x = jax.nn.selu(conv2d(x, layer["kernel"], spec.stride, spec.padding) + layer["bias"])
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


def conv_transpose(x: jax.Array, kernel: jax.Array, stride: int, padding: int) -> jax.Array:
    """PyTorch `ConvTranspose2d` semantics on NHWC: out = (in - 1) * stride - 2 * padding + k.

    Every input pixel scatters `x @ kernel` into a k x k window of the output at stride
    `stride`. Where the stride divides the kernel, that is one matrix multiply
    ([N*H*W, C_in] @ [C_in, k*k*C_out]) followed by an overlap-add: output row s*j + r
    collects window rows q*s + r from input rows j - q, so each of the s*s output phases is a
    sum of (k/s)^2 shifted copies, interleaved depth-to-space. No multiply touches the zeros
    of a dilated input, and the gradient is again pads, slices and matrix multiplies.
    Other strides use the dilated formulation (the gradient of a strided convolution).
    """
    k, _, c_in, c_out = kernel.shape
    pad = k - 1 - padding
    if pad < 0:
        raise ValueError(f"transposed convolution needs padding <= kernel - 1, got {padding} for {k}")
    if k % stride:
        return jax.lax.conv_general_dilated(
            x, kernel[::-1, ::-1], window_strides=(1, 1), padding=[(pad, pad)] * 2,
            lhs_dilation=(stride, stride), dimension_numbers=_DIMS,
        )
    n, h, w, _ = x.shape
    q = k // stride
    y = x.reshape(-1, c_in) @ kernel.transpose(2, 0, 1, 3).reshape(c_in, k * k * c_out)
    y = y.reshape(n, h, w, q, stride, q, stride, c_out)
    full = None
    for qy in range(q):
        for qx in range(q):
            shifted = jnp.pad(y[:, :, :, qy, :, qx], ((0, 0), (qy, q - 1 - qy), (qx, q - 1 - qx), (0, 0), (0, 0), (0, 0)))
            full = shifted if full is None else full + shifted
    rows, cols = (h + q - 1) * stride, (w + q - 1) * stride
    full = full.transpose(0, 1, 3, 2, 4, 5).reshape(n, rows, cols, c_out)
    return full[:, padding: rows - padding, padding: cols - padding]


def obs_decoder_logits(params: Params, arch: ArchConfig, codes: jax.Array) -> jax.Array:
    """D_o before its output sigmoid: codes `[B, obs_code]` -> logits `[B, H, W]`."""
    layers = _decoder_layers(arch)
    x = codes.reshape(codes.shape[0], 1, 1, codes.shape[-1])
    for i, (spec, _, _) in enumerate(layers):
        layer = params[f"deconv{i}"]
        x = conv_transpose(x, layer["kernel"], spec.stride, spec.padding) + layer["bias"]
        if i < len(layers) - 1:
            x = jax.nn.selu(x)
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
    z = x @ params["w_input"] + state.h @ params["w_recurrent"] + params["bias"]
    f, i, o, u = jnp.split(z, 4, axis=-1)
    c = jax.nn.sigmoid(f) * state.c + jax.nn.sigmoid(i) * jnp.tanh(u)
    h = jax.nn.sigmoid(o) * jnp.tanh(c)
    return LSTMState(h, c)
