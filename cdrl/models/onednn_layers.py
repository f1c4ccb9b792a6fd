"""The convolution layers of `--conv onednn`: `cdrl.models.onednn_conv`'s custom calls wired
into `jax.custom_vjp` by `cdrl.models.conv`'s `_conv_pair`, each pass a leaf with its batching
rule (`conv._leaf`). `conv.conv2d`, `conv_transpose`, `conv2d_selu` and `conv_transpose_selu`
call them where the backend is oneDNN, through `conv.BACKEND_LAYERS`, where importing this
module (`cdrl.models` does) registers them.

A transposed convolution is the input gradient of the strided one with the kernel's channel
axes swapped, so the three custom calls of `onednn_conv` serve both layers and their
gradients. A SELU layer's forward is one call with the bias and SELU inside: the strided
convolution's, or for a transposed layer oneDNN's deconvolution (the input-gradient primitive
takes no post-ops; the thesis decoder's 32 -> 16 channel, 20 -> 38 layer over 32 frames, forward
and backward, took 8.1 ms with a second pass for the bias and SELU, 4.9 ms fused:
`benchmarks/layer_timings.py --onednn`). One pass stays on XLA: an input
gradient onto a single channel (the thesis decoder's last layer forward, 16 -> 1: 4.6 ms with
the sub-pixel form against 6.2 ms on oneDNN over 32 frames, 37 against 51 ms over 256).
"""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from cdrl.models import onednn_conv
from cdrl.models.conv import (BACKEND_LAYERS, BackendLayers, _conv_pair, _flip_io, _leaf, _transposed_by,
                              _xla_input_grad)


@_leaf(grouped=True)
def _onednn_forward(x: jax.Array, kernel: jax.Array, stride: int, padding: int) -> jax.Array:
    return onednn_conv.forward(x, kernel, stride, padding)


@_leaf(grouped=True)
def _onednn_input_grad(dy: jax.Array, kernel: jax.Array, stride: int, padding: int, h: int, w: int) -> jax.Array:
    return onednn_conv.input_grad(dy, kernel, stride, padding, (h, w))


@_leaf(foldable=False, grouped=True)
def _onednn_kernel_grad(x: jax.Array, dy: jax.Array, k: int, stride: int, padding: int) -> jax.Array:
    return onednn_conv.kernel_grad(x, dy, k, stride, padding)


def _input_grad(dy: jax.Array, kernel: jax.Array, stride: int, padding: int, h: int, w: int) -> jax.Array:
    """d<conv2d(x, kernel), dy>/dx for x of spatial size h x w: on oneDNN, or onto a single
    channel by XLA's sub-pixel form (where the stride divides the kernel)."""
    if kernel.shape[2] > 1 or kernel.shape[0] % stride:
        return _onednn_input_grad(dy, kernel, stride, padding, h, w)
    return _xla_input_grad(dy, kernel, stride, padding, h, w)


strided, transposed = _conv_pair(_onednn_forward, _input_grad, _onednn_kernel_grad)


# SELU(z) = λ z for z > 0, λ α (e^z - 1) else; its derivative, λ or λ α e^z = y + λ α, is a
# function of the output y: the backward passes need no pre-activation and no exponential.
_SELU_ALPHA = 1.6732632423543772
_SELU_SCALE = 1.0507009873554805


def _selu_grad(y: jax.Array, ct: jax.Array) -> jax.Array:
    return ct * jnp.where(y > 0, _SELU_SCALE, y + _SELU_SCALE * _SELU_ALPHA)


@_leaf(grouped=True)
def _onednn_forward_selu(x: jax.Array, kernel_bias, stride: int, padding: int) -> jax.Array:
    return onednn_conv.forward_selu(x, kernel_bias[0], kernel_bias[1], stride, padding)


@partial(jax.custom_vjp, nondiff_argnums=(3, 4))
def strided_selu(x, kernel, bias, stride, padding):
    return _onednn_forward_selu(x, (kernel, bias), stride, padding)


def _strided_selu_fwd(x, kernel, bias, stride, padding):
    y = _onednn_forward_selu(x, (kernel, bias), stride, padding)
    return y, (x, kernel, y)


def _strided_selu_bwd(stride, padding, res, ct):
    x, kernel, y = res
    dz = _selu_grad(y, ct)
    dx = _input_grad(dz, kernel, stride, padding, x.shape[1], x.shape[2])
    return dx, _onednn_kernel_grad(x, dz, kernel.shape[0], stride, padding), dz.sum((0, 1, 2))


strided_selu.defvjp(_strided_selu_fwd, _strided_selu_bwd)


@_leaf(grouped=True)
def _onednn_bias_selu(z: jax.Array, bias: jax.Array) -> jax.Array:
    return onednn_conv.bias_selu(z, bias)


@_leaf(grouped=True)
def _onednn_input_grad_selu(dy: jax.Array, kernel_bias, stride: int, padding: int, h: int, w: int) -> jax.Array:
    return onednn_conv.input_grad_selu(dy, kernel_bias[0], kernel_bias[1], stride, padding, (h, w))


def _input_grad_selu(dy, kernel, bias, stride, padding, h, w):
    """SELU(the input gradient + bias): in one oneDNN deconvolution, or onto a single channel by
    XLA's sub-pixel form and a second pass for the bias and SELU."""
    if kernel.shape[2] > 1 or kernel.shape[0] % stride:
        return _onednn_input_grad_selu(dy, (kernel, bias), stride, padding, h, w)
    return _onednn_bias_selu(_xla_input_grad(dy, kernel, stride, padding, h, w), bias)


def _transposed_selu_out(x, kernel, bias, stride, padding):
    return _transposed_by(lambda *a: _input_grad_selu(a[0], a[1], bias, *a[2:]), x, kernel, stride, padding)


@partial(jax.custom_vjp, nondiff_argnums=(3, 4))
def transposed_selu(x, kernel, bias, stride, padding):
    return _transposed_selu_out(x, kernel, bias, stride, padding)


def _transposed_selu_fwd(x, kernel, bias, stride, padding):
    y = _transposed_selu_out(x, kernel, bias, stride, padding)
    return y, (x, kernel, y)


def _transposed_selu_bwd(stride, padding, res, ct):
    x, kernel, y = res
    dz = _selu_grad(y, ct)
    dx = _onednn_forward(dz, _flip_io(kernel), stride, padding)
    dk = _flip_io(_onednn_kernel_grad(dz, x, kernel.shape[0], stride, padding))
    return dx, dk, dz.sum((0, 1, 2))


transposed_selu.defvjp(_transposed_selu_fwd, _transposed_selu_bwd)


BACKEND_LAYERS["onednn"] = BackendLayers(strided, transposed, strided_selu, transposed_selu)
