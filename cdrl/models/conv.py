"""Strided and transposed convolutions (NHWC), each pass in the formulation XLA's CPU backend
runs fastest; on other backends (GPU, TPU) XLA's native convolutions and their own gradients,
which cuDNN and the TPU's convolution units run directly (`formulation`).

A convolution and its transpose are each other's input gradient, so the two share three
primitives, chosen by per-layer measurement at the thesis's size (`benchmarks/layer_timings.py`
times every layer; the figures below are from that machine, 2 cores):

* the strided convolution: XLA's native `conv_general_dilated` (its forward is fast: 18 ms for
  the 16 -> 16 channel 76 -> 38 layer over 256 frames, where the patches-and-matrix-multiply
  form took 270 ms);
* the transposed convolution: the sub-pixel form, one native stride-1 convolution with a
  (k/s) x (k/s) window and s*s*C_out output channels, then depth-to-space. Output row s*j + r
  of the transposed convolution collects kernel row q*s + r from input row j - q, so each of the
  s*s output phases is an ordinary convolution of the input (56 ms for 16 -> 16, 38 -> 76
  over 256 frames, against 324 ms for XLA's dilated-input form and 150 ms for the
  matrix-multiply overlap-add form);
* the kernel gradient: XLA's native kernel-gradient convolution, run over tiles of
  `KERNEL_GRAD_TILE` frames and summed. Its cost per frame grows with the batch when it runs
  over the whole batch at once (176 ms for the 76 -> 38 layer over 256 frames, 84 ms in tiles
  of 8), so tiling is what keeps a batch from costing frames per second.

Under `vmap` (a sweep's configurations) XLA's own batching rule turns a convolution whose
kernel is batched into a grouped convolution, which its CPU backend runs group by group.
Each pass here is a leaf with its own rule (`_leaf`): with only the frames batched, the
configuration axis folds into the frames; with the kernels batched too, one convolution per
configuration, unrolled for a few and by `lax.map` for many. oneDNN's passes instead take the
configurations on a leading axis in one custom call, which runs them side by side on XLA's
CPU threads (nested `vmap`s merge into that one axis). The passes are only ever
differentiated through their `custom_vjp`, so the leaves need no derivative of their own.

The `onednn` backend (`--conv onednn`, `ArchConfig.conv`) runs the three passes as XLA custom
calls into oneDNN, the library PyTorch's CPU convolutions run on (`cdrl.models.onednn_conv`,
wired in `cdrl.models.onednn_layers`):
the strided forward, the input gradient (which is also the transposed forward) and the kernel
gradient. `conv2d_selu` and `conv_transpose_selu` also put the bias and SELU into oneDNN, and
read SELU's derivative off the layer's output. The thesis-sized model then trains 1.2-2.0
times as fast as in the formulation above (`benchmarks/train_throughput.py --onednn`). Without
the extension it falls back to "cpu".

`jax.custom_vjp` wires them (`_conv_pair`, for both backends): the gradient of `conv2d` with respect to its input is the
transposed convolution of the output gradient, and the gradient of `conv_transpose` with
respect to its input is the strided convolution of the output gradient (XLA's own rules
would run both through dilated convolutions, many times slower on the CPU). A layer whose
window covers its whole (padded) input, like the thesis's 5x5 -> 1x1 encoder layer and its
mirror, is a dense layer and runs as one matrix multiply. Strides that do not divide the
kernel use XLA's convolutions as they are.
"""
from __future__ import annotations

import os
from functools import partial
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from cdrl.models import onednn_conv

_DIMS = ("NHWC", "HWIO", "NHWC")
FORMULATIONS = ("auto", "cpu", "native", "onednn")
# The formulation "auto" traces: "auto" (the default) picks by the default backend; "cpu",
# "native" or "onednn" forces one (the environment variable CDRL_CONV_FORMULATION sets it at
# import). A run's `--conv` (`ArchConfig.conv`) names one for its own layers.
FORMULATION = os.environ.get("CDRL_CONV_FORMULATION", "auto")
# Frames per tile of the kernel-gradient convolution, and the most tiles one gradient is
# split into (beyond, tiles grow: the tiles are unrolled in the program, so their number
# bounds the compile time).
KERNEL_GRAD_TILE = 8
MAX_KERNEL_GRAD_TILES = 32
# Under `vmap`, configurations up to this many run as unrolled convolutions; more by `lax.map`.
MAX_UNROLLED_CONFIGS = 8


def _leaf(fn=None, *, foldable: bool = True, grouped: bool = False):
    """`fn(a, b, *static)` with a batching rule of its own (see the module docstring): a
    convolution pass whose first argument holds independent frames on its leading axis
    (`foldable`: the pass is frame by frame, so a batch of configurations folds into the
    frames while `b` is shared) and whose second is a kernel (or a tuple of arrays, as a
    kernel and its bias), or for the kernel gradient the other operand of a sum over the
    frames (not foldable). A `grouped` pass also takes a leading axis of configurations on `a`
    and every leaf of `b`, and runs them in one call (oneDNN's passes, side by side)."""
    if fn is None:
        return partial(_leaf, foldable=foldable, grouped=grouped)

    def per_config(axis_size, a, b, static):
        if grouped:
            return call_grouped(a, b, *static)
        if axis_size <= MAX_UNROLLED_CONFIGS:
            return jnp.stack([call(a[i], jax.tree.map(lambda leaf: leaf[i], b), *static) for i in range(axis_size)])
        return jax.lax.map(lambda ab: call(ab[0], ab[1], *static), (a, b))

    def call(a, b, *static):
        @jax.custom_batching.custom_vmap
        def leaf(a, b):
            return fn(a, b, *static)

        @leaf.def_vmap
        def rule(axis_size, in_batched, a, b):
            a_batched, b_batched = in_batched
            if foldable and a_batched and not any(jax.tree.leaves(b_batched)):
                y = call(a.reshape((-1,) + a.shape[2:]), b, *static)
                return y.reshape((axis_size, a.shape[1]) + y.shape[1:]), True
            a, b = _broadcast(axis_size, a, b, in_batched)
            return per_config(axis_size, a, b, static), True

        return leaf(a, b)

    def call_grouped(a, b, *static):
        @jax.custom_batching.custom_vmap
        def leaf(a, b):
            return fn(a, b, *static)

        @leaf.def_vmap
        def rule(axis_size, in_batched, a, b):
            # A further axis of configurations merges with the first.
            a, b = _broadcast(axis_size, a, b, in_batched)
            merge = lambda leaf: leaf.reshape((-1,) + leaf.shape[2:])
            y = call_grouped(merge(a), jax.tree.map(merge, b), *static)
            return y.reshape((axis_size, a.shape[1]) + y.shape[1:]), True

        return leaf(a, b)

    call.__doc__, call.__name__ = fn.__doc__, fn.__name__
    return call


def _broadcast(axis_size: int, a, b, in_batched):
    """`a` and the leaves of `b`, each with a leading axis of `axis_size` (broadcast where not batched)."""
    grow = lambda leaf, batched: leaf if batched else jnp.broadcast_to(leaf, (axis_size,) + leaf.shape)
    return grow(a, in_batched[0]), jax.tree.map(grow, b, in_batched[1])


def _native(x: jax.Array, kernel: jax.Array, stride: int, padding: int) -> jax.Array:
    return jax.lax.conv_general_dilated(x, kernel, (stride, stride), [(padding, padding)] * 2,
                                        dimension_numbers=_DIMS)


def _fold(x: jax.Array, k: int, stride: int, padding: int, h_out: int, w_out: int) -> jax.Array:
    """The padded input rows and columns that `h_out` x `w_out` windows read, folded
    space-to-depth by the stride: [N, H, W, C] -> [N, h_out - 1 + k/s, w_out - 1 + k/s, s*s*C],
    channels ordered (row phase, column phase, C)."""
    n, h, w, c = x.shape
    s, q = stride, k // stride
    rows, cols = (h_out - 1 + q) * s, (w_out - 1 + q) * s
    x = jnp.pad(x, ((0, 0), (padding, max(0, rows - h - padding)), (padding, max(0, cols - w - padding)), (0, 0)))
    x = x[:, :rows, :cols].reshape(n, rows // s, s, cols // s, s, c).transpose(0, 1, 3, 2, 4, 5)
    return x.reshape(n, rows // s, cols // s, s * s * c)


def _out_size(size: int, k: int, stride: int, padding: int) -> int:
    return (size + 2 * padding - k) // stride + 1


@_leaf
def _space_to_depth_conv(x: jax.Array, kernel: jax.Array, stride: int, padding: int) -> jax.Array:
    """The strided convolution as a stride-1 one with a (k/s) x (k/s) window on the input
    folded space-to-depth (for strides that divide the kernel)."""
    k, _, c_in, c_out = kernel.shape
    s, q = stride, k // stride
    folded = _fold(x, k, s, padding, _out_size(x.shape[1], k, s, padding), _out_size(x.shape[2], k, s, padding))
    # kernel[qy*s + ry, qx*s + rx, c, o] -> [qy, qx, (ry, rx, c), o], like the folded channels.
    kernel = kernel.reshape(q, s, q, s, c_in, c_out).transpose(0, 2, 1, 3, 4, 5).reshape(q, q, s * s * c_in, c_out)
    return jax.lax.conv_general_dilated(folded, kernel, (1, 1), "VALID", dimension_numbers=_DIMS)


@_leaf
def _native_leaf(x: jax.Array, kernel: jax.Array, stride: int, padding: int) -> jax.Array:
    return _native(x, kernel, stride, padding)


def _strided_forward(x: jax.Array, kernel: jax.Array, stride: int, padding: int) -> jax.Array:
    # A single input channel gives XLA's convolution nothing to vectorise over; folded
    # space-to-depth it has s*s (the thesis's first layer over 32 frames: 2.6 ms against 3.8 ms).
    if x.shape[-1] == 1:
        return _space_to_depth_conv(x, kernel, stride, padding)
    return _native_leaf(x, kernel, stride, padding)


def _flip_io(kernel: jax.Array) -> jax.Array:
    """[kh, kw, a, b] -> [kh, kw, b, a]: a convolution's kernel as its transpose's, and back."""
    return kernel.transpose(0, 1, 3, 2)


@_leaf(foldable=False)
def _kernel_grad_tile(x: jax.Array, ct: jax.Array, k: int, stride: int, padding: int) -> jax.Array:
    """d<conv2d(x, kernel), ct>/d kernel as one convolution, written in the layout XLA's CPU
    backend runs through its Eigen convolution: the frames are the contracted feature axis
    and the input channels the batch axis. (XLA's own rule leaves this layout to a layout
    pass that does not reach convolutions inside a `lax.scan`, where the naive loop it falls
    back to is tens of times slower.) With a single frame that contraction has length one and
    (k/s)^2 matrix products over the folded input are faster (the 76 -> 38 layer: 0.5 ms
    against 1.3 ms): a closed loop's step runs its convolutions on one frame per stream."""
    _, h, w, c_in = x.shape
    _, ho, wo, c_out = ct.shape
    if x.shape[0] == 1:
        s, q = stride, k // stride
        folded = _fold(x, k, s, padding, ho, wo)[0]
        taps = [jnp.einsum("yxc,yxo->co", folded[a: a + ho, b: b + wo], ct[0]) for a in range(q) for b in range(q)]
        # [(qy, qx), (ry, rx, c), o] -> [qy*s + ry, qx*s + rx, c, o]
        g = jnp.stack(taps).reshape(q, q, s, s, c_in, c_out).transpose(0, 2, 1, 3, 4, 5)
        return g.reshape(k, k, c_in, c_out)
    # Output size k = h + lo + hi - ((ho - 1) * stride + 1) + 1.
    pads = [(padding, k + (ho - 1) * stride - h - padding), (padding, k + (wo - 1) * stride - w - padding)]
    g = jax.lax.conv_general_dilated(x.transpose(3, 1, 2, 0), ct.transpose(1, 2, 0, 3), (1, 1), pads,
                                     rhs_dilation=(stride, stride), dimension_numbers=_DIMS)
    return g.transpose(1, 2, 0, 3)  # [C_in, k, k, C_out] -> [k, k, C_in, C_out]


def _kernel_grad(x: jax.Array, ct: jax.Array, k: int, stride: int, padding: int) -> jax.Array:
    """d<conv2d(x, kernel), ct>/d kernel, tile by tile of frames, summed."""
    n = x.shape[0]
    tile = max(KERNEL_GRAD_TILE, -(-n // MAX_KERNEL_GRAD_TILES))
    total = None
    for start in range(0, n, tile):
        grad = _kernel_grad_tile(x[start: start + tile], ct[start: start + tile], k, stride, padding)
        total = grad if total is None else total + grad
    return total


@_leaf
def _subpixel_full(x: jax.Array, kernel: jax.Array, stride: int) -> jax.Array:
    """The transposed convolution (kernel [kh, kw, in, out]) before any crop, (h - 1) * s + k
    rows, as one stride-1 convolution with s*s*out channels and depth-to-space (for strides
    that divide the kernel)."""
    k, _, c_in, c_out = kernel.shape
    n, h, w, _ = x.shape
    s, q = stride, k // stride
    # Correlation tap a of phase r reads input row j + a - (q - 1), i.e. kernel row (q-1-a)*s + r.
    taps = kernel.reshape(q, s, q, s, c_in, c_out)[::-1, :, ::-1]
    taps = taps.transpose(0, 2, 4, 1, 3, 5).reshape(q, q, c_in, s * s * c_out)
    y = jax.lax.conv_general_dilated(x, taps, (1, 1), [(q - 1, q - 1)] * 2, dimension_numbers=_DIMS)
    rows, cols = (h + q - 1) * s, (w + q - 1) * s
    return y.reshape(n, h + q - 1, w + q - 1, s, s, c_out).transpose(0, 1, 3, 2, 4, 5).reshape(n, rows, cols, c_out)


def _xla_input_grad(dy: jax.Array, kernel: jax.Array, stride: int, padding: int, h: int, w: int) -> jax.Array:
    """d<conv2d(x, kernel), dy>/dx for x of spatial size h x w: the full transposed convolution
    covers the padded input up to the last window's end; drop the leading padding, keep h rows
    (rows past the last window get no gradient)."""
    dx = _subpixel_full(dy, _flip_io(kernel), stride)[:, padding: padding + h, padding: padding + w]
    return jnp.pad(dx, ((0, 0), (0, h - dx.shape[1]), (0, w - dx.shape[2]), (0, 0)))


def _transposed_by(input_grad, x, kernel, stride, padding):
    """PyTorch's transposed convolution (kernel [kh, kw, in, out]) as the input gradient of the
    strided convolution whose kernel has the two channel axes swapped."""
    k = kernel.shape[0]
    h, w = ((size - 1) * stride - 2 * padding + k for size in x.shape[1:3])
    return input_grad(x, _flip_io(kernel), stride, padding, h, w)


def _conv_pair(forward, input_grad, kernel_grad):
    """The strided convolution and its transpose from three passes, `forward(x, kernel, s, p)`,
    `input_grad(dy, kernel, s, p, h, w)` and `kernel_grad(x, dy, k, s, p)`, each wired by
    `jax.custom_vjp`: the gradient of one with respect to its input is the other."""

    @partial(jax.custom_vjp, nondiff_argnums=(2, 3))
    def strided(x, kernel, stride, padding):
        return forward(x, kernel, stride, padding)

    def strided_fwd(x, kernel, stride, padding):
        return forward(x, kernel, stride, padding), (x, kernel)

    def strided_bwd(stride, padding, res, ct):
        x, kernel = res
        dx = input_grad(ct, kernel, stride, padding, x.shape[1], x.shape[2])
        return dx, kernel_grad(x, ct, kernel.shape[0], stride, padding)

    @partial(jax.custom_vjp, nondiff_argnums=(2, 3))
    def transposed(x, kernel, stride, padding):
        return _transposed_by(input_grad, x, kernel, stride, padding)

    def transposed_fwd(x, kernel, stride, padding):
        return _transposed_by(input_grad, x, kernel, stride, padding), (x, kernel)

    def transposed_bwd(stride, padding, res, ct):
        # <conv_transpose(x, K), ct> = <x, conv2d(ct, K with in and out swapped)>.
        x, kernel = res
        dx = forward(ct, _flip_io(kernel), stride, padding)
        return dx, _flip_io(kernel_grad(ct, x, kernel.shape[0], stride, padding))

    strided.defvjp(strided_fwd, strided_bwd)
    transposed.defvjp(transposed_fwd, transposed_bwd)
    return strided, transposed


_strided, _transposed = _conv_pair(_strided_forward, _xla_input_grad, _kernel_grad)


class BackendLayers(NamedTuple):
    """A backend's convolution layers, each with its `jax.custom_vjp`: `strided(x, kernel, s, p)`,
    `transposed(x, kernel, s, p)`, and `strided_selu` / `transposed_selu(x, kernel, bias, s, p)`
    (SELU(layer + bias))."""

    strided: Callable
    transposed: Callable
    strided_selu: Callable
    transposed_selu: Callable


# The backends beyond XLA's own, by formulation name; `cdrl.models.onednn_layers` registers
# "onednn" (it builds on this module's passes, so this module does not import it).
BACKEND_LAYERS: dict[str, BackendLayers] = {}


def formulation(name: str = "auto") -> str:
    """The formulation `name` traces: "auto" is `FORMULATION` (the environment variable
    CDRL_CONV_FORMULATION), and where that is "auto" too, "cpu" (this module's, chosen by timing
    XLA's CPU backend) when JAX's default backend is the CPU and "native" (XLA's convolutions as
    they are) on any other. "onednn" where `onednn_conv.available()`, else "cpu" with one
    warning. Chosen when a function is traced; a run passes its `--conv` as
    `ArchConfig.conv`, a static field, so programs of different backends are kept apart."""
    for given in (name, FORMULATION):
        if given not in FORMULATIONS:
            raise ValueError(f"conv formulation must be one of {', '.join(FORMULATIONS)}, got {given!r} "
                             "(--conv, or the environment variable CDRL_CONV_FORMULATION)")
    name = FORMULATION if name == "auto" else name
    if name == "onednn" and not onednn_conv.available():
        onednn_conv.warn_unavailable()
        return "cpu"
    if name != "auto":
        return name
    return "cpu" if jax.default_backend() == "cpu" else "native"


def _native_transpose(x: jax.Array, kernel: jax.Array, stride: int, padding: int) -> jax.Array:
    """The transposed convolution as XLA's input-dilated convolution with the flipped kernel."""
    pad = kernel.shape[0] - 1 - padding
    return jax.lax.conv_general_dilated(x, kernel[::-1, ::-1], window_strides=(1, 1), padding=[(pad, pad)] * 2,
                                        lhs_dilation=(stride, stride), dimension_numbers=_DIMS)


def conv2d(x: jax.Array, kernel: jax.Array, stride: int, padding: int, backend: str = "auto") -> jax.Array:
    """Strided convolution: NHWC input, HWIO kernel, symmetric zero padding (see the module
    docstring for the formulation of each pass, `formulation` for `backend`)."""
    form = formulation(backend)
    if form == "native":
        return _native(x, kernel, stride, padding)
    k, _, c_in, c_out = kernel.shape
    n, h, w, _ = x.shape
    if h + 2 * padding == k and w + 2 * padding == k:  # one window: a dense layer
        x = jnp.pad(x, ((0, 0), (padding, padding), (padding, padding), (0, 0)))
        return (x.reshape(n, k * k * c_in) @ kernel.reshape(k * k * c_in, c_out)).reshape(n, 1, 1, c_out)
    if form == "onednn":
        return BACKEND_LAYERS["onednn"].strided(x, kernel, stride, padding)
    if k % stride:
        return _native(x, kernel, stride, padding)
    return _strided(x, kernel, stride, padding)


def conv2d_selu(x: jax.Array, kernel: jax.Array, bias: jax.Array, stride: int, padding: int,
                backend: str = "auto") -> jax.Array:
    """SELU(conv2d(x, kernel) + bias). On oneDNN, for a strided layer, one custom call with the
    bias and SELU inside, whose backward reads SELU's derivative off its output. A layer whose
    window covers its input stays a matrix product (oneDNN's convolution ran the thesis's
    5 x 5 -> 1 x 1 layer about 2.5 times slower in the train step)."""
    k = kernel.shape[0]
    dense = x.shape[1] + 2 * padding == k and x.shape[2] + 2 * padding == k
    if formulation(backend) == "onednn" and not dense:
        return BACKEND_LAYERS["onednn"].strided_selu(x, kernel, bias, stride, padding)
    return jax.nn.selu(conv2d(x, kernel, stride, padding, backend) + bias)


def conv_transpose_selu(x: jax.Array, kernel: jax.Array, bias: jax.Array, stride: int, padding: int,
                        backend: str = "auto") -> jax.Array:
    """SELU(conv_transpose(x, kernel) + bias). On oneDNN, for a layer of more than one input
    pixel: one deconvolution with the bias and SELU as post-ops; the backward reads SELU's
    derivative off the output."""
    if formulation(backend) == "onednn" and x.shape[1] * x.shape[2] > 1 and padding <= kernel.shape[0] - 1:
        return BACKEND_LAYERS["onednn"].transposed_selu(x, kernel, bias, stride, padding)
    return jax.nn.selu(conv_transpose(x, kernel, stride, padding, backend) + bias)


def conv_transpose(x: jax.Array, kernel: jax.Array, stride: int, padding: int,
                   backend: str = "auto") -> jax.Array:
    """PyTorch `ConvTranspose2d` semantics on NHWC, kernel [kh, kw, in, out] (PyTorch's weight
    [in, out, kh, kw]): out = (in - 1) * stride - 2 * padding + k. Every input pixel scatters
    `x @ kernel` into a k x k window of the output at stride `stride`."""
    k, _, c_in, c_out = kernel.shape
    if k - 1 - padding < 0:
        raise ValueError(f"transposed convolution needs padding <= kernel - 1, got {padding} for {k}")
    form = formulation(backend)
    if form == "native":
        return _native_transpose(x, kernel, stride, padding)
    n, h, w, _ = x.shape
    if h == 1 and w == 1:  # one input pixel: a dense layer onto the k x k window
        y = x.reshape(n, c_in) @ kernel.transpose(2, 0, 1, 3).reshape(c_in, k * k * c_out)
        return y.reshape(n, k, k, c_out)[:, padding: k - padding, padding: k - padding]
    if form == "onednn":
        return BACKEND_LAYERS["onednn"].transposed(x, kernel, stride, padding)
    if k % stride:
        return _native_transpose(x, kernel, stride, padding)
    return _transposed(x, kernel, stride, padding)
