"""oneDNN's convolutions (`--conv onednn`, `cdrl.models.onednn_conv`) against XLA's: values and
both gradients of every pass, at the thesis's layer shapes, under `jit`, `vmap`, `grad` and
`lax.scan`; a train step of the tiny model; and the fallback where the extension is missing
(`CDRL_ONEDNN=0` turns it off).
The tests that need the extension are skipped where it is not built (CI runs the suite without
it too)."""
import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdrl.models import conv, onednn_conv
from cdrl.models.arch import preset
from jaxprs import equations

needs_onednn = pytest.mark.skipif(not onednn_conv.available(), reason=str(onednn_conv.unavailable_reason()))


def _xla(kind, stride, padding):
    """XLA's own convolutions and their own gradients: the independent path."""
    dims = ("NHWC", "HWIO", "NHWC")
    if kind == "conv":
        return lambda x, k: jax.lax.conv_general_dilated(x, k, (stride, stride), [(padding, padding)] * 2,
                                                         dimension_numbers=dims)
    pad = lambda k: k.shape[0] - 1 - padding  # noqa: E731
    return lambda x, k: jax.lax.conv_general_dilated(x, k[::-1, ::-1], (1, 1), [(pad(k), pad(k))] * 2,
                                                     lhs_dilation=(stride, stride), dimension_numbers=dims)


def _onednn(kind, stride, padding):
    fn = conv.conv2d if kind == "conv" else conv.conv_transpose
    return lambda x, k: fn(x, k, stride, padding, "onednn")


def _value_and_grads(f, x, k, ct):
    y, vjp = jax.vjp(f, x, k)
    return (y, *vjp(ct))


def _assert_close(got, want, what):
    for name, g, w in zip(("value", "input gradient", "kernel gradient"), got, want):
        assert g.shape == w.shape, (what, name)
        np.testing.assert_allclose(g, w, rtol=1e-4, atol=1e-4 * float(jnp.abs(w).max()), err_msg=f"{what}: {name}")


def _thesis_layers():
    """(kind, c_in, c_out, size, kernel, stride, padding) of every strided layer of the thesis's
    encoder and decoder that oneDNN runs (the dense ends are matrix products either way)."""
    arch = preset("thesis")
    from cdrl.models.nets import _decoder_layers

    layers, c_in = [], 1
    for spec, size in zip(arch.encoder, arch.encoder_sizes):
        if size + 2 * spec.padding > spec.kernel:
            layers.append(("conv", c_in, spec.features, size, spec.kernel, spec.stride, spec.padding))
        c_in = spec.features
    for (spec, ci, co), size in zip(_decoder_layers(arch), arch.decoder_sizes):
        if size > 1:
            layers.append(("transpose", ci, co, size, spec.kernel, spec.stride, spec.padding))
    return layers


@needs_onednn
@pytest.mark.parametrize("layer", _thesis_layers(), ids=lambda l: f"{l[0]}{l[1]}-{l[2]}@{l[3]}")
def test_every_thesis_layer_equals_xla(layer):
    kind, c_in, c_out, size, k, stride, padding = layer
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.normal(size=(2, size, size, c_in)), jnp.float32)
    kernel = jnp.asarray(rng.normal(size=(k, k, c_in, c_out)) / np.sqrt(k * k * c_in), jnp.float32)
    y = _xla(kind, stride, padding)(x, kernel)
    ct = jnp.asarray(rng.normal(size=y.shape), jnp.float32)
    want = jax.jit(functools.partial(_value_and_grads, _xla(kind, stride, padding)))(x, kernel, ct)
    got = jax.jit(functools.partial(_value_and_grads, _onednn(kind, stride, padding)))(x, kernel, ct)
    _assert_close(got, want, str(layer))


@needs_onednn
# a stride that does not divide the kernel, one that does not divide h + 2p - k, a single
# frame, a single channel in and out, the tiny preset's layers
@pytest.mark.parametrize("kind,size,k,stride,padding,n,c_in,c_out",
                         [("conv", 9, 3, 2, 1, 2, 3, 5), ("conv", 7, 4, 2, 1, 1, 3, 5), ("conv", 15, 4, 2, 2, 2, 1, 4),
                          ("transpose", 6, 3, 2, 0, 2, 3, 2), ("transpose", 8, 4, 2, 2, 1, 3, 1),
                          ("transpose", 9, 8, 4, 2, 2, 2, 1)])
def test_odd_shapes_equal_xla(kind, size, k, stride, padding, n, c_in, c_out):
    rng = np.random.default_rng(1)
    x = jnp.asarray(rng.normal(size=(n, size, size, c_in)), jnp.float32)
    kernel = jnp.asarray(rng.normal(size=(k, k, c_in, c_out)), jnp.float32)
    y = _xla(kind, stride, padding)(x, kernel)
    ct = jnp.asarray(rng.normal(size=y.shape), jnp.float32)
    _assert_close(_value_and_grads(_onednn(kind, stride, padding), x, kernel, ct),
                  _value_and_grads(_xla(kind, stride, padding), x, kernel, ct), kind)


@needs_onednn
@pytest.mark.parametrize("kind", ["conv", "transpose"])
@pytest.mark.parametrize("shared_kernel", [False, True])
def test_vmap_and_scan_equal_the_pass_per_configuration(kind, shared_kernel):
    """Under `vmap` over configurations (the batching rule of `conv._leaf`), and inside a
    `lax.scan` over steps, values and gradients equal XLA's path one configuration at a time."""
    rng = np.random.default_rng(2)
    configs, steps, size = 3, 2, (12 if kind == "conv" else 6)
    x = jnp.asarray(rng.normal(size=(configs, steps, 2, size, size, 4)), jnp.float32)
    shape = (4, 4, 4, 5)
    kernel = jnp.asarray(rng.normal(size=shape if shared_kernel else (configs,) + shape), jnp.float32)

    def loss(layer, xs, k):
        def body(total, x):
            return total + jnp.sum(jnp.sin(layer(x, k))), None
        return jax.lax.scan(body, 0.0, xs)[0]

    grad = lambda layer: jax.value_and_grad(functools.partial(loss, layer), argnums=(0, 1))  # noqa: E731
    k_axis = None if shared_kernel else 0
    got_v, (got_dx, got_dk) = jax.jit(jax.vmap(grad(_onednn(kind, 2, 1)), (0, k_axis)))(x, kernel)
    for i in range(configs):
        want_v, (want_dx, want_dk) = grad(_xla(kind, 2, 1))(x[i], kernel if shared_kernel else kernel[i])
        np.testing.assert_allclose(got_v[i], want_v, rtol=1e-4)
        np.testing.assert_allclose(got_dx[i], want_dx, rtol=1e-4, atol=1e-4)
        if not shared_kernel:
            np.testing.assert_allclose(got_dk[i], want_dk, rtol=1e-4, atol=1e-3)
    if shared_kernel:  # the kernel's gradient sums the configurations'
        want = sum(grad(_xla(kind, 2, 1))(x[i], kernel)[1][1] for i in range(configs))
        np.testing.assert_allclose(got_dk.sum(0) if got_dk.ndim == 5 else got_dk, want, rtol=1e-4, atol=1e-3)


@needs_onednn
def test_a_train_step_and_its_checkpoint_are_the_same_on_both_backends():
    """The tiny model's train step from one state gives the same loss and parameters with
    `ArchConfig.conv` "cpu" and "onednn" (only the second calls oneDNN): the parameters, so a
    checkpoint, do not depend on the backend."""
    import dataclasses

    from cdrl.data.stream import Chunk
    from cdrl.models import TINY, make_variant
    from cdrl.training.step import HParams, init_state, train_step

    rng = np.random.default_rng(3)
    t, b, size = 4, 2, TINY.image_size
    frames = rng.integers(0, 256, size=(t + 1, b, size, size), dtype=np.uint8)
    chunk = Chunk(obs=jnp.asarray(frames[:-1]), next_obs=jnp.asarray(frames[1:]),
                  action=jnp.zeros((t, b, 3), jnp.float32), reward=jnp.zeros((t, b), jnp.float32),
                  is_first=jnp.zeros((t, b), bool).at[0].set(True))
    results = {}
    for name in ("cpu", "onednn"):
        variant = make_variant("main", dataclasses.replace(TINY, conv=name))
        state, hp = init_state(variant, jax.random.PRNGKey(0), b), HParams.create(variant)
        program = train_step.lower(variant, state, hp, chunk).as_text()
        assert ("cdrl_onednn_conv" in program) == (name == "onednn")
        results[name] = train_step(variant, state, hp, chunk)
    (cpu_state, cpu_out), (dnnl_state, dnnl_out) = results["cpu"], results["onednn"]
    assert jax.tree.structure(cpu_state.params) == jax.tree.structure(dnnl_state.params)
    np.testing.assert_allclose(dnnl_out["loss"], cpu_out["loss"], rtol=1e-5)
    for got, want in zip(jax.tree.leaves(dnnl_state.params), jax.tree.leaves(cpu_state.params)):
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)


def test_onednn_falls_back_to_xla_with_one_warning(monkeypatch):
    """Where the extension is not there, `onednn` traces XLA's CPU formulation and warns once."""
    monkeypatch.delenv("CDRL_ONEDNN", raising=False)  # CI runs this file with the extension off too
    monkeypatch.setattr(onednn_conv, "_extension_path", lambda: None)
    monkeypatch.setattr(onednn_conv, "_load", onednn_conv._load.__wrapped__)  # uncached: sees the missing file
    onednn_conv.warn_unavailable.cache_clear()
    try:
        assert not onednn_conv.available()
        assert "not built" in onednn_conv.unavailable_reason()
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            assert conv.formulation("onednn") == conv.formulation("onednn") == "cpu"
        messages = [str(w.message) for w in seen if "'onednn' is not available" in str(w.message)]
        assert len(messages) == 1 and "not built" in messages[0]
    finally:
        onednn_conv.warn_unavailable.cache_clear()


def test_a_run_records_its_convolution_backend():
    """`--conv` is a model option: checked, in the run's config.json and in its architecture
    (a static field: programs of the two backends are compiled apart)."""
    from cdrl.runs.config import RunConfig

    cfg = RunConfig(conv="onednn")
    assert cfg.arch.conv == "onednn" and cfg.to_dict()["model"]["conv"] == "onednn"
    assert hash(cfg.arch) != hash(RunConfig().arch)
    with pytest.raises(ValueError, match="conv must be one of auto, cpu, native, onednn"):
        RunConfig(conv="mkl")


@needs_onednn
# sizes 2 and 1: a window that covers the whole input, a transposed layer from one pixel
@pytest.mark.parametrize("kind,size,padding", [("conv", 12, 1), ("conv", 76, 1), ("conv", 2, 1), ("conv", 38, 2),
                                               ("transpose", 6, 1), ("transpose", 20, 1), ("transpose", 1, 1),
                                               ("transpose", 20, 2)])
@pytest.mark.parametrize("batched", ["none", "frames", "all"])
def test_the_fused_selu_layer_equals_its_parts(kind, size, padding, batched):
    """SELU(convolution + bias) on oneDNN (the bias and SELU inside the convolution, SELU's
    derivative read off the output) equals XLA's layer written out, in values and in the
    gradients of the input, kernel and bias; also under `vmap` over frames alone or over
    frames, kernels and biases."""
    rng = np.random.default_rng(4)
    c_in, c_out, k, stride = 4, 6, 4, 2
    configs = 2
    shape = (configs, 3, size, size, c_in) if batched != "none" else (3, size, size, c_in)
    x = jnp.asarray(rng.normal(size=shape), jnp.float32)
    k_shape = (configs, k, k, c_in, c_out) if batched == "all" else (k, k, c_in, c_out)
    kernel = jnp.asarray(rng.normal(size=k_shape) / 8, jnp.float32)
    bias = jnp.asarray(rng.normal(size=k_shape[:-4] + (c_out,)), jnp.float32)
    fused = conv.conv2d_selu if kind == "conv" else conv.conv_transpose_selu

    def loss(layer, x, kernel, bias):
        return jnp.sum(jnp.sin(layer(x, kernel, bias)))

    mine = lambda x, kr, b: fused(x, kr, b, stride, padding, "onednn")  # noqa: E731
    theirs = lambda x, kr, b: jax.nn.selu(_xla(kind, stride, padding)(x, kr) + b)  # noqa: E731
    grads = lambda layer: jax.value_and_grad(functools.partial(loss, layer), argnums=(0, 1, 2))  # noqa: E731
    if batched == "none":
        got, want = grads(mine)(x, kernel, bias), grads(theirs)(x, kernel, bias)
    else:
        axes = (0, 0, 0) if batched == "all" else (0, None, None)
        got = jax.jit(jax.vmap(grads(mine), axes))(x, kernel, bias)
        want = jax.vmap(grads(theirs), axes)(x, kernel, bias)
    for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
        np.testing.assert_allclose(g, w, rtol=1e-4, atol=1e-4 * float(jnp.abs(w).max()))


@needs_onednn
@pytest.mark.parametrize("kind", ["conv", "transpose"])
def test_vmapped_configurations_run_as_one_call_per_pass(kind):
    """Under `vmap` over configurations with their own kernels, each pass is one custom call
    whose operands carry the configurations on a leading axis (run side by side in C++), not
    one call per configuration."""
    configs = 5
    x = jnp.zeros((configs, 2, 12 if kind == "conv" else 6, 12 if kind == "conv" else 6, 4))
    kernel = jnp.zeros((configs, 4, 4, 4, 5))
    grad = jax.grad(lambda x, k: jnp.sum(_onednn(kind, 2, 1)(x, k)), argnums=(0, 1))
    calls = equations(jax.make_jaxpr(jax.vmap(grad))(x, kernel).jaxpr, "ffi_call")
    assert len(calls) == 3, [e.params.get("call_target_name") for e in calls]  # forward, input and kernel grads
    assert all(v.aval.shape[0] == configs and v.aval.ndim == 5 for e in calls for v in e.invars)


@needs_onednn
def test_nested_vmaps_of_configurations_equal_xla_one_at_a_time():
    """Two nested `vmap`s (say seeds within learning rates) merge into one axis of 6
    configurations; the fused SELU layer and both gradients equal XLA's per configuration."""
    rng = np.random.default_rng(5)
    outer, inner, frames, size, c_in, c_out = 2, 3, 2, 12, 4, 6
    x = jnp.asarray(rng.normal(size=(outer, inner, frames, size, size, c_in)), jnp.float32)
    kernel = jnp.asarray(rng.normal(size=(outer, inner, 4, 4, c_in, c_out)) / 8, jnp.float32)
    bias = jnp.asarray(rng.normal(size=(outer, 1, c_out)), jnp.float32)  # shared by the inner axis

    def loss(layer, x, k, b):
        return jnp.sum(jnp.sin(layer(x, k, b)))

    mine = lambda x, k, b: conv.conv2d_selu(x, k, b, 2, 1, "onednn")  # noqa: E731
    theirs = lambda x, k, b: jax.nn.selu(_xla("conv", 2, 1)(x, k) + b)  # noqa: E731
    grads = lambda layer: jax.value_and_grad(functools.partial(loss, layer), argnums=(0, 1, 2))  # noqa: E731
    got = jax.jit(jax.vmap(jax.vmap(grads(mine), (0, 0, None)), (0, 0, 0)))(x, kernel, bias[:, 0])
    for i in range(outer):
        for j in range(inner):
            want = grads(theirs)(x[i, j], kernel[i, j], bias[i, 0])
            g = jax.tree.map(lambda a: a[i, j], got)
            for gl, wl in zip(jax.tree.leaves(g), jax.tree.leaves(want)):
                np.testing.assert_allclose(gl, wl, rtol=1e-4, atol=1e-4 * float(jnp.abs(wl).max()))


@needs_onednn
@pytest.mark.parametrize("kind", ["conv", "transpose"])
def test_the_passes_run_inside_shard_map(kind):
    """Inside `jax.shard_map` (a sweep sharded over devices or processes) the custom calls'
    results vary over the mesh axis as their operands do; values and gradients equal XLA's.
    A mesh of one device checks the types as one of many does."""
    from jax.sharding import PartitionSpec as P

    rng = np.random.default_rng(6)
    size = 12 if kind == "conv" else 6
    x = jnp.asarray(rng.normal(size=(2, 3, size, size, 4)), jnp.float32)
    kernel = jnp.asarray(rng.normal(size=(2, 4, 4, 4, 5)), jnp.float32)
    mesh = jax.make_mesh((1,), ("config",), devices=jax.devices()[:1])
    x, kernel = jax.device_put((x, kernel), jax.sharding.NamedSharding(mesh, P("config")))

    def per_config(layer):
        grads = jax.value_and_grad(lambda x, k: jnp.sum(jnp.sin(layer(x, k))), argnums=(0, 1))
        return jax.shard_map(jax.vmap(grads), mesh=mesh, in_specs=P("config"), out_specs=P("config"))

    got = jax.jit(per_config(_onednn(kind, 2, 1)))(x, kernel)
    want = per_config(_xla(kind, 2, 1))(x, kernel)
    for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
        np.testing.assert_allclose(g, w, rtol=1e-4, atol=1e-4 * float(jnp.abs(w).max()))


_THREADED = '''
import jax, jax.numpy as jnp, numpy as np
from cdrl.models import conv
rng = np.random.default_rng(7)
for configs in (2, 6):  # fewer configurations than threads: one after another with a team; more: side by side
    x = jnp.asarray(rng.normal(size=(configs, 3, 12, 12, 4)), jnp.float32)
    k = jnp.asarray(rng.normal(size=(configs, 4, 4, 4, 5)) / 8, jnp.float32)
    b = jnp.asarray(rng.normal(size=(configs, 5)), jnp.float32)
    def grads(backend):
        f = lambda x, k, b: jnp.sum(jnp.sin(conv.conv_transpose_selu(conv.conv2d_selu(x, k, b, 2, 1, backend),
                                                                      k.swapaxes(2, 3), b[:4], 2, 1, backend)))
        return jax.jit(jax.vmap(jax.value_and_grad(f, argnums=(0, 1, 2))))(x, k, b)
    for g, w in zip(jax.tree.leaves(grads("onednn")), jax.tree.leaves(grads("cpu"))):
        np.testing.assert_allclose(g, w, rtol=1e-4, atol=1e-4 * float(jnp.abs(w).max()))
print("OK")
'''


@needs_onednn
def test_configurations_on_more_threads_than_cores_equal_xla():
    """With 4 oneDNN threads and every pass counted large, 2 configurations run one after another
    on a team and 6 side by side on XLA's threads: both equal XLA's formulation."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "CDRL_ONEDNN_THREADS": "4", "CDRL_ONEDNN_PARALLEL_MACS": "1"}
    out = subprocess.run([sys.executable, "-c", _THREADED], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip().endswith("OK"), out.stderr[-3000:]
