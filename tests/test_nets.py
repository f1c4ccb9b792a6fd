"""The networks against their definitions: layer sizes, transposed-convolution semantics,
the LSTM against the thesis's equations, initialisation scales, errors on bad configs."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdrl.models import make_variant, nets
from cdrl.models.arch import THESIS, ArchConfig, ConvSpec, preset
from cdrl.models.base import StepInput


def test_thesis_table_sizes():
    arch = THESIS
    assert arch.encoder_sizes == (150, 76, 38, 20, 10, 5, 1)
    assert arch.decoder_sizes == (1, 5, 10, 20, 38, 76, 150)
    assert [s.features for s in arch.encoder] == [16, 16, 32, 64, 128, 512]
    assert [(s.kernel, s.stride, s.padding) for s in arch.encoder] == [
        (4, 2, 2), (4, 2, 1), (4, 2, 2), (4, 2, 1), (4, 2, 1), (5, 1, 0)
    ]


def test_every_intermediate_size_of_the_thesis_networks():
    """Run the real layers one by one (abstractly) and pin each output shape."""
    arch = THESIS
    params = jax.eval_shape(lambda: {
        "enc": nets.init_obs_encoder(jax.random.PRNGKey(0), arch),
        "dec": nets.init_obs_decoder(jax.random.PRNGKey(0), arch),
    })
    x = jax.ShapeDtypeStruct((1, 150, 150, 1), jnp.float32)
    enc_shapes = []
    for i, spec in enumerate(arch.encoder):
        x = jax.eval_shape(
            lambda x, k: jax.lax.conv_general_dilated(
                x, k, (spec.stride,) * 2, [(spec.padding,) * 2] * 2,
                dimension_numbers=("NHWC", "HWIO", "NHWC")),
            x, params["enc"][f"conv{i}"]["kernel"])
        enc_shapes.append(x.shape[1:])
    assert enc_shapes == [(76, 76, 16), (38, 38, 16), (20, 20, 32), (10, 10, 64), (5, 5, 128), (1, 1, 512)]
    dec_shapes = []
    for i, spec in enumerate(reversed(arch.encoder)):
        x = jax.eval_shape(lambda x, k: nets.conv_transpose(x, k, spec.stride, spec.padding),
                           x, params["dec"][f"deconv{i}"]["kernel"])
        dec_shapes.append(x.shape[1:])
    assert dec_shapes == [(5, 5, 128), (10, 10, 64), (20, 20, 32), (38, 38, 16), (76, 76, 16), (150, 150, 1)]


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


@pytest.mark.parametrize("size,kernel,stride,padding", [(150, 4, 2, 2), (7, 4, 2, 1), (5, 5, 1, 0), (9, 3, 2, 1), (8, 4, 4, 0)])
def test_matmul_convolution_equals_xla_convolution(size, kernel, stride, padding):
    """The space-to-depth matrix-multiply convolution against XLA's, values and gradients."""
    rng = np.random.default_rng(1)
    x = jnp.asarray(rng.normal(size=(2, size, size, 3)), jnp.float32)
    k = jnp.asarray(rng.normal(size=(kernel, kernel, 3, 5)), jnp.float32)

    def xla(x, k):
        return jax.lax.conv_general_dilated(x, k, (stride, stride), [(padding, padding)] * 2,
                                            dimension_numbers=("NHWC", "HWIO", "NHWC"))

    def mine(x, k):
        return nets.conv2d(x, k, stride, padding)

    np.testing.assert_allclose(mine(x, k), xla(x, k), rtol=1e-4, atol=1e-4)
    cot = jnp.asarray(rng.normal(size=xla(x, k).shape), jnp.float32)
    for got, want in zip(jax.vjp(mine, x, k)[1](cot), jax.vjp(xla, x, k)[1](cot)):
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-3)


def test_matmul_conv_transpose_gradient_equals_dilated_form():
    rng = np.random.default_rng(2)
    x = jnp.asarray(rng.normal(size=(2, 10, 10, 3)), jnp.float32)
    k = jnp.asarray(rng.normal(size=(4, 4, 3, 2)), jnp.float32)

    def dilated(x, k):
        return jax.lax.conv_general_dilated(x, k[::-1, ::-1], (1, 1), [(2, 2)] * 2, lhs_dilation=(2, 2),
                                            dimension_numbers=("NHWC", "HWIO", "NHWC"))

    out = nets.conv_transpose(x, k, 2, 1)
    cot = jnp.asarray(rng.normal(size=out.shape), jnp.float32)
    np.testing.assert_allclose(out, dilated(x, k), rtol=1e-4, atol=1e-4)
    for got, want in zip(jax.vjp(lambda a, b: nets.conv_transpose(a, b, 2, 1), x, k)[1](cot),
                         jax.vjp(dilated, x, k)[1](cot)):
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-3)


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
    one step from a zero carry gives a 150x150 frame in (0, 1)."""
    v = make_variant("main_action", THESIS)
    params = jax.jit(v.init)(jax.random.PRNGKey(0))
    x = StepInput(obs=jnp.full((1, 150, 150), 0.5), action=jnp.full((1, 3), 0.5),
                           is_first=jnp.ones((1,), bool))
    carry, out = jax.jit(v.step)(params, v.init_carry(1), x)
    assert out["logits"].shape == (1, 150, 150)
    assert out["code"].shape == (1, 512 + 16) and out["pred_code"].shape == (1, 512)
    assert carry.h.shape == (1, 512)
    pred = jax.nn.sigmoid(out["logits"])
    assert bool(jnp.all((pred > 0) & (pred < 1)))
    assert float(jnp.std(out["logits"])) > 0


def test_bad_architecture_is_rejected():
    with pytest.raises(ValueError, match="reduce the 100x100 image to 1x1"):
        ArchConfig(image_size=100)
    with pytest.raises(ValueError, match="unknown architecture preset 'huge'"):
        preset("huge")
    with pytest.raises(ValueError, match="rebuild 8x8"):
        ArchConfig(image_size=8, encoder=(ConvSpec(4, 3, 2, 0), ConvSpec(8, 3, 1, 0)))
