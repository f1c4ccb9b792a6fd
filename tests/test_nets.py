"""The networks against their definitions: layer sizes, transposed-convolution semantics,
the LSTM against the thesis's equations, initialisation scales, errors on bad configs."""
import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdrl.models import make_variant, nets
from cdrl.models.arch import THESIS, ArchConfig, ConvSpec, preset
from cdrl.models.base import StepInput, bce_with_logits


def test_thesis_table_sizes():
    arch = THESIS
    assert arch.encoder_sizes == (150, 76, 38, 20, 10, 5, 1)
    assert arch.decoder_sizes == (1, 5, 10, 20, 38, 76, 150)
    assert [s.features for s in arch.encoder] == [16, 16, 32, 64, 128, 512]
    assert [(s.kernel, s.stride, s.padding) for s in arch.encoder] == [
        (4, 2, 2), (4, 2, 1), (4, 2, 2), (4, 2, 1), (4, 2, 1), (5, 1, 0)
    ]


def _naive_conv_transpose(x, kernel, stride, padding):
    """PyTorch ConvTranspose2d by its definition: scatter every input pixel times the kernel."""
    n, h, w, _ = x.shape
    k = kernel.shape[0]
    full = np.zeros((n, (h - 1) * stride + k, (w - 1) * stride + k, kernel.shape[3]))
    for i in range(h):
        for j in range(w):
            full[:, i * stride:i * stride + k, j * stride:j * stride + k] += np.einsum(
                "nc,yxco->nyxo", x[:, i, j], kernel)
    return full[:, padding:full.shape[1] - padding, padding:full.shape[2] - padding]


def _selu(x):
    """SELU by its definition (Klambauer et al. 2017), float64."""
    alpha, scale = 1.6732632423543772, 1.0507009873554805
    return scale * np.where(x > 0, x, alpha * np.expm1(np.minimum(x, 0)))


def _xla_conv(x, kernel, stride, padding):
    return jax.lax.conv_general_dilated(x, kernel, (stride, stride), [(padding, padding)] * 2,
                                        dimension_numbers=("NHWC", "HWIO", "NHWC"))


def test_every_intermediate_size_of_the_thesis_networks():
    """Run the real layers, `nets.conv2d` and `nets.conv_transpose`, one by one on thesis-sized
    inputs: each output's shape is the thesis table's (150 -> 76 -> 38 -> 20 -> 10 -> 5 -> 1
    and back), each output's values equal an independent reference (XLA's convolution in
    float64; the transposed convolution by its definition, in float64), and
    `nets.obs_encoder` / `nets.obs_decoder_logits` equal the layers chained with SELU."""
    arch = THESIS
    rng = np.random.default_rng(0)
    conv2d = jax.jit(nets.conv2d, static_argnums=(2, 3))
    conv_transpose = jax.jit(nets.conv_transpose, static_argnums=(2, 3))

    def layer(k, c_in, c_out):  # LeCun-scaled kernel, non-zero bias (the chained networks must add it)
        return {"kernel": jnp.asarray(rng.normal(0, (k * k * c_in) ** -0.5, (k, k, c_in, c_out)), jnp.float32),
                "bias": jnp.asarray(rng.normal(0, 0.1, c_out), jnp.float32)}

    # The parameter trees as the layer table gives them (random values: the eager
    # initialisers take seconds at this size); the decoder mirrors the encoder.
    chans = [1, 16, 16, 32, 64, 128, 512]
    enc = {f"conv{i}": layer(s.kernel, chans[i], chans[i + 1]) for i, s in enumerate(arch.encoder)}
    dec = {f"deconv{i}": layer(s.kernel, chans[-1 - i], chans[-2 - i]) for i, s in enumerate(reversed(arch.encoder))}
    shapes = jax.eval_shape(lambda: (nets.init_obs_encoder(jax.random.PRNGKey(0), arch),
                                     nets.init_obs_decoder(jax.random.PRNGKey(0), arch)))
    assert jax.tree.map(lambda a: a.shape, shapes) == jax.tree.map(lambda a: a.shape, (enc, dec))

    frames = rng.uniform(size=(1, 150, 150)).astype(np.float32)
    x = frames[..., None].astype(np.float64)
    enc_shapes = []
    for i, spec in enumerate(arch.encoder):
        layer = enc[f"conv{i}"]
        got = np.asarray(conv2d(jnp.asarray(x, jnp.float32), layer["kernel"], spec.stride, spec.padding))
        with jax.enable_x64(True):
            want = np.asarray(_xla_conv(jnp.asarray(x), jnp.asarray(layer["kernel"], jnp.float64),
                                        spec.stride, spec.padding))
        assert got.shape == want.shape, (i, got.shape, want.shape)
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5 * np.abs(want).max(), err_msg=f"conv{i}")
        enc_shapes.append(got.shape[1:])
        x = _selu(want + np.asarray(layer["bias"], np.float64))
    assert enc_shapes == [(76, 76, 16), (38, 38, 16), (20, 20, 32), (10, 10, 64), (5, 5, 128), (1, 1, 512)]
    code = np.asarray(jax.jit(nets.obs_encoder, static_argnums=1)(enc, arch, jnp.asarray(frames)))
    np.testing.assert_allclose(code, x.reshape(1, -1), rtol=1e-4, atol=1e-5 * np.abs(x).max())

    dec_shapes = []
    for i, spec in enumerate(reversed(arch.encoder)):
        layer = dec[f"deconv{i}"]
        got = np.asarray(conv_transpose(jnp.asarray(x, jnp.float32), layer["kernel"], spec.stride, spec.padding))
        want = _naive_conv_transpose(x, np.asarray(layer["kernel"], np.float64), spec.stride, spec.padding)
        assert got.shape == want.shape, (i, got.shape, want.shape)
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5 * np.abs(want).max(), err_msg=f"deconv{i}")
        dec_shapes.append(got.shape[1:])
        x = want + np.asarray(layer["bias"], np.float64)
        if i < len(arch.encoder) - 1:
            x = _selu(x)
    assert dec_shapes == [(5, 5, 128), (10, 10, 64), (20, 20, 32), (38, 38, 16), (76, 76, 16), (150, 150, 1)]
    logits = np.asarray(jax.jit(nets.obs_decoder_logits, static_argnums=1)(dec, arch, jnp.asarray(code)))
    np.testing.assert_allclose(logits, x[..., 0], rtol=1e-4, atol=1e-4 * np.abs(x).max())


@pytest.mark.default_opt
@pytest.mark.parametrize("size,kernel,stride,padding", [(5, 4, 2, 1), (19, 4, 2, 2), (1, 5, 1, 0), (6, 3, 2, 0)])
def test_conv_transpose_matches_its_definition(size, kernel, stride, padding):
    rng = np.random.default_rng(0)
    x = rng.normal(size=(2, size, size, 3)).astype(np.float32)
    k = rng.normal(size=(kernel, kernel, 3, 4)).astype(np.float32)
    got = np.asarray(nets.conv_transpose(jnp.asarray(x), jnp.asarray(k), stride, padding))
    want = _naive_conv_transpose(x.astype(np.float64), k.astype(np.float64), stride, padding)
    assert got.shape == want.shape
    assert got.shape[1] == got.shape[2] == (size - 1) * stride - 2 * padding + kernel
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)


def _xla_conv_transpose(stride, padding):
    def f(x, k):
        pad = k.shape[0] - 1 - padding
        return jax.lax.conv_general_dilated(x, k[::-1, ::-1], (1, 1), [(pad, pad)] * 2, lhs_dilation=(stride, stride),
                                            dimension_numbers=("NHWC", "HWIO", "NHWC"))
    return f


def _assert_same_function(mine, xla, x, k, seed):
    """Values and both gradients (input and kernel) of `mine` against XLA's convolution."""
    np.testing.assert_allclose(mine(x, k), xla(x, k), rtol=1e-4, atol=1e-4)
    cot = jnp.asarray(np.random.default_rng(seed).normal(size=xla(x, k).shape), jnp.float32)
    got, want = jax.vjp(mine, x, k)[1](cot), jax.vjp(xla, x, k)[1](cot)
    for name, g, w in zip(("input", "kernel"), got, want):
        assert g.shape == w.shape, name
        np.testing.assert_allclose(g, w, rtol=1e-4, atol=1e-3 * float(jnp.abs(w).max()), err_msg=name)


@pytest.mark.default_opt
# (150, 4, 2, 2): the thesis's first layer; (7, 4, 2, 1): a stride that does not divide
# h + 2p - k (the last input row is never read: zero gradient); (5, 5, 1, 0): a dense layer;
# (9, 3, 2, 1): a stride that does not divide the kernel; batch 20: three kernel-gradient tiles;
# one input channel: the space-to-depth forward; batch 1: the single-frame kernel gradient.
@pytest.mark.parametrize("size,kernel,stride,padding,batch,c_in",
                         [(150, 4, 2, 2, 2, 3), (7, 4, 2, 1, 2, 3), (5, 5, 1, 0, 2, 3), (9, 3, 2, 1, 2, 3),
                          (8, 4, 4, 0, 2, 3), (12, 4, 2, 1, 20, 3), (15, 4, 2, 2, 2, 1), (7, 4, 2, 1, 2, 1),
                          (12, 4, 2, 1, 1, 3), (7, 4, 2, 1, 1, 3), (36, 8, 4, 2, 2, 1)])
def test_convolution_equals_xla_convolution(size, kernel, stride, padding, batch, c_in):
    rng = np.random.default_rng(1)
    x = jnp.asarray(rng.normal(size=(batch, size, size, c_in)), jnp.float32)
    k = jnp.asarray(rng.normal(size=(kernel, kernel, c_in, 5)), jnp.float32)
    _assert_same_function(lambda a, b: nets.conv2d(a, b, stride, padding), lambda a, b: _xla_conv(a, b, stride, padding), x, k, 2)


@pytest.mark.default_opt
@pytest.mark.parametrize("size,kernel,stride,padding,batch,c_out",
                         [(10, 4, 2, 1, 2, 2), (19, 4, 2, 2, 2, 2), (1, 5, 1, 0, 2, 2), (6, 3, 2, 0, 2, 2),
                          (9, 4, 2, 1, 20, 2), (8, 4, 2, 2, 2, 1), (9, 4, 2, 1, 1, 2), (10, 4, 2, 2, 1, 1),
                          (9, 8, 4, 2, 2, 1)])
def test_conv_transpose_equals_xla_dilated_form(size, kernel, stride, padding, batch, c_out):
    rng = np.random.default_rng(2)
    x = jnp.asarray(rng.normal(size=(batch, size, size, 3)), jnp.float32)
    k = jnp.asarray(rng.normal(size=(kernel, kernel, 3, c_out)), jnp.float32)
    _assert_same_function(lambda a, b: nets.conv_transpose(a, b, stride, padding),
                          _xla_conv_transpose(stride, padding), x, k, 3)


@pytest.mark.parametrize("backend,expected", [("cpu", "cpu"), ("gpu", "native"), ("tpu", "native")])
def test_the_convolutions_are_chosen_by_backend(monkeypatch, backend, expected):
    """On the CPU the custom formulations (the gradient through `custom_vjp`, the transposed
    convolution in sub-pixel form); on GPU and TPU XLA's native convolutions as they are, the
    transposed one input-dilated, with XLA's own gradients; both the same function."""
    from cdrl.models import conv

    monkeypatch.setattr(conv.jax, "default_backend", lambda: backend)
    assert conv.formulation() == expected
    rng = np.random.default_rng(6)
    x = jnp.asarray(rng.normal(size=(2, 10, 10, 3)), jnp.float32)
    k = jnp.asarray(rng.normal(size=(4, 4, 3, 5)), jnp.float32)
    strided = str(jax.make_jaxpr(lambda x, k: nets.conv2d(x, k, 2, 1))(x, k))
    transposed = str(jax.make_jaxpr(lambda x, k: nets.conv_transpose(x, k, 2, 1))(x, k))
    assert ("custom_vjp" in strided) == ("custom_vjp" in transposed) == (expected == "cpu")
    assert ("lhs_dilation=(2, 2)" in transposed) == (expected == "native")
    _assert_same_function(lambda a, b: nets.conv2d(a, b, 2, 1), lambda a, b: _xla_conv(a, b, 2, 1), x, k, 7)
    monkeypatch.setattr(conv, "FORMULATION", "fast")
    with pytest.raises(ValueError, match="conv formulation must be one of auto, cpu, native, onednn"):
        conv.formulation()


@pytest.mark.default_opt
def test_kernel_gradient_tiles_cover_the_batch(monkeypatch):
    """Tiles of 2 frames, at most 3 tiles: 20 frames go in 3 tiles of 7, 7 and 6."""
    from cdrl.models import conv

    monkeypatch.setattr(conv, "KERNEL_GRAD_TILE", 2)
    monkeypatch.setattr(conv, "MAX_KERNEL_GRAD_TILES", 3)
    rng = np.random.default_rng(4)
    x = jnp.asarray(rng.normal(size=(20, 12, 12, 3)), jnp.float32)
    k = jnp.asarray(rng.normal(size=(4, 4, 3, 5)), jnp.float32)
    jaxpr = str(jax.make_jaxpr(jax.grad(lambda k: jnp.sum(nets.conv2d(x, k, 2, 1) ** 2)))(k))
    assert jaxpr.count("f32[7,12,12,3]") >= 2 and "f32[6,12,12,3]" in jaxpr
    _assert_same_function(lambda a, b: nets.conv2d(a, b, 2, 1), lambda a, b: _xla_conv(a, b, 2, 1), x, k, 5)


def _plain_autoencoder(params, arch, frames):
    """E_o then D_o written out layer by layer: no recomputed layers, one pass."""
    x = (frames[..., None] - arch.obs_mean) / arch.obs_std
    for i, spec in enumerate(arch.encoder):
        x = jax.nn.selu(nets.conv2d(x, params["obs_enc"][f"conv{i}"]["kernel"], spec.stride, spec.padding)
                        + params["obs_enc"][f"conv{i}"]["bias"])
    x = x.reshape(x.shape[0], 1, 1, -1)
    layers = nets._decoder_layers(arch)
    for i, (spec, _, _) in enumerate(layers):
        layer = params["obs_dec"][f"deconv{i}"]
        x = nets.conv_transpose(x, layer["kernel"], spec.stride, spec.padding) + layer["bias"]
        x = jax.nn.selu(x) if i < len(layers) - 1 else x
    return x[..., 0]


def test_recomputed_layers_and_encoder_passes_change_no_value_or_gradient(monkeypatch):
    """The image-sized layers recomputed in the backward pass, and a chunk's frames encoded in
    passes (7 frames in passes of 3: two passes and a remainder of 1), against the autoencoder
    written out plainly: the same predictions, the same gradient. (Both only where those
    layers are large: forced here on the tiny preset.)"""
    from cdrl.models import base

    monkeypatch.setattr(base, "ENCODER_PASS_FRAMES", 3)
    arch = preset("tiny")
    v = make_variant("baseline_ff", arch)
    params = v.init(jax.random.PRNGKey(3))
    frames = jax.random.uniform(jax.random.PRNGKey(4), (7, 1, arch.image_size, arch.image_size))
    target = jax.random.uniform(jax.random.PRNGKey(5), frames.shape)

    def loss(p, decode):
        return jnp.mean(bce_with_logits(decode(p), target))

    def library(p):
        return v.decode(p, v.encode(p, frames, None))

    def plain(p):
        return _plain_autoencoder(p, arch, frames.reshape(7, *frames.shape[2:])).reshape(frames.shape)

    def gradient_jaxpr():
        return str(jax.make_jaxpr(jax.grad(lambda p: loss(p, library)))(params))

    # Small layers are kept, not recomputed, and encoded in one pass.
    assert not nets.recomputes_image_layers(arch) and nets.recomputes_image_layers(THESIS)
    assert "remat" not in gradient_jaxpr() and "scan" not in gradient_jaxpr()
    monkeypatch.setattr(nets, "RECOMPUTE_FROM_BYTES", 0)
    np.testing.assert_allclose(library(params), plain(params), rtol=1e-5, atol=1e-5)
    got, want = jax.grad(loss)(params, library), jax.grad(loss)(params, plain)
    for path, g in jax.tree_util.tree_leaves_with_path(got):
        w = dict(jax.tree_util.tree_leaves_with_path(want))[path]
        np.testing.assert_allclose(g, w, rtol=1e-4, atol=1e-6, err_msg=jax.tree_util.keystr(path))
    jaxpr = gradient_jaxpr()
    assert jaxpr.count("remat") >= 2 and "scan" in jaxpr  # the two recomputed layers; the passes


def test_lstm_cell_equals_thesis_equations():
    """Eq. 3.4 with separate per-gate weight matrices, computed in float64 numpy."""
    rng = np.random.default_rng(1)
    n_in, n_h, batch = 5, 7, 3
    params = nets.init_lstm(jax.random.PRNGKey(0), n_in, n_h)
    params["bias"] = jnp.asarray(rng.normal(size=4 * n_h), jnp.float32)
    x = rng.normal(size=(batch, n_in)).astype(np.float32)
    h0 = rng.normal(size=(batch, n_h)).astype(np.float32)
    c0 = rng.normal(size=(batch, n_h)).astype(np.float32)
    state = nets.lstm_cell(params, nets.LSTMState(jnp.asarray(h0), jnp.asarray(c0)), jnp.asarray(x))

    wi, wr, b = (np.asarray(params[k], np.float64) for k in ("w_input", "w_recurrent", "bias"))
    gate = {name: slice(g * n_h, (g + 1) * n_h) for g, name in enumerate(["f", "i", "o", "C"])}
    sig = lambda z: 1 / (1 + np.exp(-z))  # noqa: E731

    def pre(name):
        s = gate[name]
        return x @ wi[:, s] + h0 @ wr[:, s] + b[s]

    f, i, o = sig(pre("f")), sig(pre("i")), sig(pre("o"))
    c = f * c0 + i * np.tanh(pre("C"))
    h = o * np.tanh(c)
    np.testing.assert_allclose(np.asarray(state.c), c, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(state.h), h, rtol=1e-5, atol=1e-6)


def _lstm_by_steps(params, state, xs, is_first):
    """The LSTM over time as a Python loop over `lstm_cell`, the state zero at each episode start."""
    states = []
    for t in range(xs.shape[0]):
        state = jax.tree.map(lambda a: jnp.where(is_first[t][:, None], 0.0, a), state)
        state = nets.lstm_cell(params, state, xs[t])
        states.append(state)
    return state, jax.tree.map(lambda *a: jnp.stack(a), *states)


def test_lstm_unroll_equals_its_steps_in_values_and_gradients():
    """`lstm_unroll` hoists the input product and sums the recurrent kernel's gradient after its
    scan: the values and every gradient equal a loop over `lstm_cell`, under jit, grad and vmap."""
    T, B, n_in, n_h = 7, 3, 5, 4
    keys = jax.random.split(jax.random.PRNGKey(3), 5)
    params = nets.init_lstm(keys[0], n_in, n_h)
    params["bias"] = jax.random.normal(keys[1], params["bias"].shape)
    xs = jax.random.normal(keys[2], (T, B, n_in))
    is_first = jnp.asarray(np.random.default_rng(0).uniform(size=(T, B)) < 0.25)
    state = nets.LSTMState(jax.random.normal(keys[3], (B, n_h)), jax.random.normal(keys[4], (B, n_h)))

    def loss(run, params, state, xs):
        final, states = run(params, state, xs, is_first)
        return jnp.sum(jnp.sin(states.h) * jnp.arange(n_h)) + jnp.sum(states.c ** 2) + jnp.sum(3 * final.h)

    fused = functools.partial(nets.lstm_unroll, unroll=2)
    for got, want in zip(jax.jit(fused)(params, state, xs, is_first), _lstm_by_steps(params, state, xs, is_first)):
        jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6), got, want)
    grad = jax.grad(loss, argnums=(1, 2, 3))
    want = grad(_lstm_by_steps, params, state, xs)
    got = jax.jit(grad, static_argnums=0)(fused, params, state, xs)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5), got, want)
    # A kernel per configuration, as a sweep has it.
    stacked = jax.tree.map(lambda a: jnp.stack([a, 1.3 * a]), params)
    per_config = jax.vmap(lambda p: jax.grad(loss, argnums=1)(fused, p, state, xs))
    for i in range(2):
        one = jax.tree.map(lambda a: a[i], stacked)
        jax.tree.map(lambda a, b: np.testing.assert_allclose(a[i], b, rtol=1e-4, atol=1e-5),
                     jax.jit(per_config)(stacked), jax.grad(loss, argnums=1)(_lstm_by_steps, one, state, xs))


def test_initialisation_scales():
    """LeCun-normal (std 1/sqrt(fan_in)) before SELU; Glorot-uniform elsewhere; zero biases."""
    arch = THESIS
    params = jax.jit(make_variant("main_action", arch).init)(jax.random.PRNGKey(0))
    k = np.asarray(params["obs_enc"]["conv4"]["kernel"])  # 4x4x64 -> 128, followed by SELU
    assert abs(k.std() * np.sqrt(4 * 4 * 64) - 1.0) < 0.1
    w = np.asarray(params["lstm"]["w_input"])  # Glorot uniform: limit sqrt(6 / (fan_in + fan_out))
    limit = np.sqrt(6 / (w.shape[0] + w.shape[1]))
    assert w.max() <= limit and w.min() >= -limit and w.max() > 0.95 * limit
    assert not np.any(np.asarray(params["obs_dec"]["deconv2"]["bias"]))
    a = np.asarray(params["act_enc"]["dense0"]["kernel"])  # 3 -> 128, SELU
    assert abs(a.std() * np.sqrt(3) - 1.0) < 0.15


def test_thesis_sized_model_one_step():
    """The full-size model (main with action: the initialiser the test above compiled already):
    its parameter count is the one the thesis's layer table gives, and one step from a zero
    carry gives a 150x150 frame in (0, 1) whose BCE against a frame is finite and, at
    initialisation (logits near 0), near ln 2."""
    v = make_variant("main_action", THESIS)
    params = jax.jit(v.init)(jax.random.PRNGKey(0))

    def conv(k, c_in, c_out):  # kernel k x k x c_in x c_out plus one bias per output channel
        return k * k * c_in * c_out + c_out

    def dense(n_in, n_out):
        return n_in * n_out + n_out

    by_hand = {
        "obs_enc": conv(4, 1, 16) + conv(4, 16, 16) + conv(4, 16, 32) + conv(4, 32, 64) + conv(4, 64, 128)
        + conv(5, 128, 512),
        "obs_dec": conv(5, 512, 128) + conv(4, 128, 64) + conv(4, 64, 32) + conv(4, 32, 16) + conv(4, 16, 16)
        + conv(4, 16, 1),
        "lstm": (512 + 16) * 4 * 512 + 512 * 4 * 512 + 4 * 512,  # input k_t = 512 + 16, LSTM 512, 4 gates
        "fc": dense(512, 512),
        "act_enc": dense(3, 128) + dense(128, 128) + dense(128, 16),
    }
    assert {k: sum(x.size for x in jax.tree.leaves(p)) for k, p in params.items()} == by_hand
    assert sum(by_hand.values()) == 6_044_305

    rng = np.random.default_rng(0)
    x = StepInput(obs=jnp.asarray(rng.uniform(size=(1, 150, 150)), jnp.float32), action=jnp.full((1, 3), 0.5),
                  is_first=jnp.ones((1,), bool))
    carry, out = jax.jit(v.step)(params, v.init_carry(1), x)
    assert out["logits"].shape == (1, 150, 150)
    assert out["code"].shape == (1, 512 + 16) and out["pred_code"].shape == (1, 512)
    assert carry.h.shape == (1, 512)
    pred = jax.nn.sigmoid(out["logits"])
    assert bool(jnp.all((pred > 0) & (pred < 1)))
    assert float(jnp.std(out["logits"])) > 0
    target = jnp.asarray(rng.uniform(size=(1, 150, 150)), jnp.float32)
    loss = float(bce_with_logits(out["logits"], target))
    assert np.isfinite(loss) and abs(loss - np.log(2)) < 0.01, loss


def test_small_128_preset_is_the_small_networks_behind_one_wider_first_layer():
    small, wide = preset("small"), preset("small-128")
    assert wide.encoder_sizes == (128, 32, 16, 8, 4, 1)
    assert wide.decoder_sizes == (1, 4, 8, 16, 32, 128)
    assert wide.encoder[1:] == small.encoder[1:] and wide.encoder[0].features == small.encoder[0].features
    assert dataclasses.replace(wide, image_size=64, encoder=small.encoder) == small


def test_small_max_preset_is_the_small_networks_seeing_through_a_max_filter():
    assert preset("small-max") == dataclasses.replace(preset("small"), max_filter=5)
    assert preset("small").max_filter == 1 and THESIS.max_filter == 1


@pytest.mark.parametrize("k", [1, 2, 3, 5])
def test_max_filter_and_resize_against_scipy(k):
    """`max_filter` is scipy's maximum filter (a window cut at the edges is scipy's nearest-edge
    padding, which adds no new value), over the last two axes of any leading shape; `resize_obs`
    shrinks what it gives with jax's antialiased linear resize, and leaves a frame at the size
    alone."""
    from scipy.ndimage import maximum_filter

    from cdrl.data.frames import max_filter, resize_obs

    frames = np.random.default_rng(k).uniform(size=(2, 3, 30, 30)).astype(np.float32)
    expected = maximum_filter(frames, size=(1, 1, k, k), mode="nearest")
    np.testing.assert_array_equal(np.asarray(max_filter(jnp.asarray(frames), k)), expected)
    shrunk = np.asarray(jax.image.resize(expected, (2, 3, 12, 12), "linear", antialias=True))
    np.testing.assert_allclose(np.asarray(resize_obs(jnp.asarray(frames), 12, k)), shrunk, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(resize_obs(jnp.asarray(frames), 30, k)), frames)


def test_bad_architecture_is_rejected():
    with pytest.raises(ValueError, match="max_filter must be >= 1"):
        ArchConfig(image_size=64, encoder=preset("small").encoder, max_filter=0)
    with pytest.raises(ValueError, match="reduce the 100x100 image to 1x1"):
        ArchConfig(image_size=100)
    with pytest.raises(ValueError, match="unknown architecture preset 'huge'"):
        preset("huge")
    with pytest.raises(ValueError, match="rebuild 8x8"):
        ArchConfig(image_size=8, encoder=(ConvSpec(4, 3, 2, 0), ConvSpec(8, 3, 1, 0)))
