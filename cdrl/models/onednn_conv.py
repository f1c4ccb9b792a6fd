"""The three passes of a strided convolution on oneDNN (PyTorch's CPU convolutions), as XLA
custom calls (`jax.ffi`).

The C++ handlers are `csrc/onednn_conv.cc`, built by the package's set-up into
`cdrl/_onednn_conv*.so` where a compiler and oneDNN's wheels (`onednn-cpu-gomp`,
`onednn-devel-cpu-gomp`) are there. `available()` says whether they loaded; without them
`cdrl.models.conv` runs its XLA formulation, with one warning when `onednn` was asked for.

Frames are NHWC and kernels HWIO, as everywhere in cdrl. Each pass takes the stride and the
leading padding; the trailing padding follows from the shapes:

* `forward(x, kernel)`: y [n, (h + 2p - k) // s + 1, ..., o];
* `forward_selu(x, kernel, bias)`: SELU(forward + bias), both inside the convolution;
* `bias_selu(z, bias)`: SELU(z + bias), one pass (after a transposed convolution);
* `input_grad(dy, kernel, (h, w))`: the gradient of the forward's input, which is also PyTorch's
  transposed convolution of `dy` with the kernel's two channel axes swapped;
* `kernel_grad(x, dy, k)`: the gradient of the forward's kernel, summed over the frames.

oneDNN runs on its own OpenMP threads, as many as XLA's CPU threads (`threads()`).
`CDRL_ONEDNN=0` in the environment leaves the extension unloaded (CI runs the tests so too).
"""
from __future__ import annotations

import ctypes
import functools
import glob
import importlib.metadata
import os
import warnings

import jax
import jax.numpy as jnp
import numpy as np

_TARGETS = {"cdrl_onednn_conv_forward": "CdrlConvForward", "cdrl_onednn_conv_input_grad": "CdrlConvInputGrad",
            "cdrl_onednn_conv_kernel_grad": "CdrlConvKernelGrad", "cdrl_onednn_conv_forward_selu": "CdrlConvForwardSelu",
            "cdrl_onednn_bias_selu": "CdrlBiasSelu", "cdrl_onednn_conv_transposed_selu": "CdrlConvTransposedSelu"}
_RUNTIME = "onednn-cpu-gomp"
# A pass of fewer multiply-adds runs on one thread (CDRL_ONEDNN_PARALLEL_MACS overrides it).
PARALLEL_MACS = 1e7  # the wheel whose libdnnl.so.3 the extension links to


def _extension_path() -> str | None:
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    found = sorted(glob.glob(os.path.join(here, "_onednn_conv*.so")))
    return found[0] if found else None


def _libdnnl_path() -> str | None:
    """libdnnl.so.3 of the `onednn-cpu-gomp` wheel (it installs into the environment's lib/)."""
    try:
        files = importlib.metadata.distribution(_RUNTIME).files or []
    except importlib.metadata.PackageNotFoundError:
        return None
    for f in files:
        if f.name == "libdnnl.so.3":
            return str(f.locate())
    return None


def threads() -> int:
    """XLA's CPU thread count: the cores this process may run on, as XLA counts them."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


@functools.lru_cache(maxsize=None)
def _load() -> str | None:
    """Loads oneDNN and the handlers and registers the custom calls once. Returns why not,
    or None where they loaded."""
    if os.environ.get("CDRL_ONEDNN", "1") == "0":
        return "turned off by the environment variable CDRL_ONEDNN=0"
    ext = _extension_path()
    if ext is None:
        return "the extension cdrl/_onednn_conv*.so is not built (no compiler or no oneDNN wheels at install)"
    dnnl = _libdnnl_path()
    try:
        if dnnl is not None:  # the extension finds libdnnl.so.3 among the loaded libraries
            ctypes.CDLL(dnnl, mode=ctypes.RTLD_GLOBAL)
        lib = ctypes.CDLL(ext)
    except OSError as e:
        return f"the oneDNN extension does not load: {e}"
    lib.CdrlOnednnSetThreads.argtypes = [ctypes.c_int, ctypes.c_double]
    lib.CdrlOnednnSetThreads(int(os.environ.get("CDRL_ONEDNN_THREADS", threads())),
                             float(os.environ.get("CDRL_ONEDNN_PARALLEL_MACS", PARALLEL_MACS)))
    for target, symbol in _TARGETS.items():
        jax.ffi.register_ffi_target(target, jax.ffi.pycapsule(getattr(lib, symbol)), platform="cpu")
    return None


def available() -> bool:
    """Whether the oneDNN passes can run here: the extension loaded and JAX runs on the CPU."""
    return _load() is None and jax.default_backend() == "cpu"


def unavailable_reason() -> str | None:
    """Why `available()` is False (None where it is True)."""
    why = _load()
    if why is None and jax.default_backend() != "cpu":
        return f"oneDNN runs on the CPU and JAX's default backend is {jax.default_backend()!r}"
    return why


@functools.lru_cache(maxsize=None)
def warn_unavailable() -> None:
    """One warning per process that `onednn` was asked for and the XLA formulation runs instead."""
    warnings.warn(f"conv formulation 'onednn' is not available ({unavailable_reason()}); "
                  "the XLA formulation runs instead", RuntimeWarning, stacklevel=3)


def _varying(operands: tuple[jax.Array, ...]) -> tuple[tuple[jax.Array, ...], dict]:
    """Inside `jax.shard_map` (a sweep over devices or processes), the operands made to vary over
    every manual mesh axis that one of them varies over, and the result's `manual_axis_type` to
    match: XLA's own operations have this rule built in, a custom call does not."""
    types = [jax.typeof(a).mat for a in operands]
    axes = frozenset().union(*(t.varying for t in types))
    if not axes:
        return operands, {}
    operands = tuple(a if t.varying == axes else jax.lax.pcast(a, tuple(axes - t.varying), to="varying")
                     for a, t in zip(operands, types))
    typed = jax.typeof(operands[0])
    return operands, {"manual_axis_type": typed.mat,
                      "sharding": jax.sharding.NamedSharding(typed.sharding.mesh, jax.sharding.PartitionSpec())}


def _call(target: str, shape, *operands: jax.Array, **attributes: int) -> jax.Array:
    _load()
    operands, manual = _varying(tuple(a.astype(jnp.float32) for a in operands))
    out = jax.ShapeDtypeStruct(tuple(int(d) for d in shape), jnp.float32, **manual)
    return jax.ffi.ffi_call(target, out, vmap_method="sequential")(
        *operands, **{name: np.int64(value) for name, value in attributes.items()})


def out_size(size: int, k: int, stride: int, padding: int) -> int:
    return (size + 2 * padding - k) // stride + 1


def forward(x: jax.Array, kernel: jax.Array, stride: int, padding: int) -> jax.Array:
    """The strided convolution of frames x [(G,) n, h, w, c] with a kernel [(G,) k, k, c, o]. A
    leading axis G holds configurations, each with its frames and kernel (a vmapped sweep);
    their convolutions run side by side."""
    *lead, h, w, _ = x.shape
    k, _, _, o = kernel.shape[-4:]
    shape = (*lead, out_size(h, k, stride, padding), out_size(w, k, stride, padding), o)
    return _call("cdrl_onednn_conv_forward", shape, x, kernel, stride=stride, padding=padding)


def forward_selu(x: jax.Array, kernel: jax.Array, bias: jax.Array, stride: int, padding: int) -> jax.Array:
    """SELU(forward(x, kernel) + bias), the bias [(G,) o] and SELU inside oneDNN's convolution."""
    *lead, h, w, _ = x.shape
    k, _, _, o = kernel.shape[-4:]
    shape = (*lead, out_size(h, k, stride, padding), out_size(w, k, stride, padding), o)
    return _call("cdrl_onednn_conv_forward_selu", shape, x, kernel, bias, stride=stride, padding=padding)


def bias_selu(z: jax.Array, bias: jax.Array) -> jax.Array:
    """SELU(z + bias) for z [(G,) n, h, w, o] and a bias [(G,) o] in one vectorised oneDNN pass."""
    return _call("cdrl_onednn_bias_selu", z.shape, z, bias)


def input_grad(dy: jax.Array, kernel: jax.Array, stride: int, padding: int, size: tuple[int, int]) -> jax.Array:
    """d<forward(x, kernel), dy>/dx for frames x of spatial `size` (h, w); dy [(G,) n, ho, wo, o]."""
    c = kernel.shape[-2]
    return _call("cdrl_onednn_conv_input_grad", (*dy.shape[:-3], *size, c), dy, kernel, stride=stride,
                 padding=padding)


def input_grad_selu(dy: jax.Array, kernel: jax.Array, bias: jax.Array, stride: int, padding: int,
                    size: tuple[int, int]) -> jax.Array:
    """SELU(input_grad(dy, kernel, ...) + bias), the bias [(G,) c] and SELU inside oneDNN's
    deconvolution: a transposed convolution's SELU layer in one pass."""
    c = kernel.shape[-2]
    return _call("cdrl_onednn_conv_transposed_selu", (*dy.shape[:-3], *size, c), dy, kernel, bias, stride=stride,
                 padding=padding)


def kernel_grad(x: jax.Array, dy: jax.Array, k: int, stride: int, padding: int) -> jax.Array:
    """d<forward(x, kernel), dy>/d kernel for a k x k kernel, summed over the frames
    (per configuration where x [G, n, h, w, c] and dy carry a leading axis G)."""
    return _call("cdrl_onednn_conv_kernel_grad", (*x.shape[:-4], k, k, x.shape[-1], dy.shape[-1]), x, dy,
                 stride=stride, padding=padding)
