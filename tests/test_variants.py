"""Every variant: its unroll equals a Python loop over its step, its gradients are right,
and its data flow is the one of the thesis (chapter 4; figures 3.2-3.5, 4.2-4.7, 6.1)."""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from cdrl.models import VARIANTS, make_variant, nets
from cdrl.models.arch import TINY
from cdrl.models.base import StepInput
from cdrl.training.optim import HParams


ARCH = TINY
NAMES = sorted(VARIANTS)


def _inputs(T=6, B=2, seed=0, dtype=jnp.float32):
    rng = np.random.default_rng(seed)
    is_first = np.zeros((T, B), bool)
    is_first[0] = True
    if T > 3:
        is_first[3, 1] = True  # stream 1 starts a new episode mid-chunk
    return StepInput(
        obs=jnp.asarray(rng.uniform(size=(T, B, ARCH.image_size, ARCH.image_size)), dtype),
        action=jnp.asarray(rng.uniform(size=(T, B, 3)), dtype),
        is_first=jnp.asarray(is_first),
    )


@pytest.mark.parametrize("name", NAMES)
def test_unroll_equals_python_loop(name):
    v = make_variant(name, ARCH)
    params = v.init(jax.random.PRNGKey(1))
    xs = _inputs()
    carry_scan, outs_scan = jax.jit(v.unroll)(params, v.init_carry(2), xs)
    carry, outs = v.init_carry(2), []
    for t in range(xs.obs.shape[0]):
        carry, out = v.step(params, carry, jax.tree.map(lambda a: a[t], xs))
        outs.append(out)
    outs_loop = jax.tree.map(lambda *a: jnp.stack(a), *outs)
    for key in outs_loop:
        np.testing.assert_allclose(outs_scan[key], outs_loop[key], rtol=1e-5, atol=1e-6, err_msg=key)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6), carry_scan, carry)


# The sign of the fed-back prediction in x_t = o_t + sign * õ_t (thesis chapter 4, figures 4.6,
# 4.7 and 6.1), written out here rather than read from the classes.
CLOSED_LOOP_SIGNS = {"closed_loop_plus": 1.0, "closed_loop_minus": -1.0, "final_proposal": -1.0}


@functools.partial(jax.jit, static_argnums=0)
def _closed_loop_step_by_hand(name, params, h, c, fed, obs, action, sign):
    """One step of one stream (batch 1) of the closed-loop data flow, composed from the
    networks of `cdrl.models.nets`: x_t = o_t + sign * õ_t; k_t = E_o(x_t) (++ E_a(a_t) for
    final_proposal); h_t = LSTM(k_t); d = FC(h_t), split for final_proposal into the
    observation, action and reward codes; logits = D_o(observation code); õ_{t+1} =
    sigmoid(logits)."""
    arch = ARCH
    k = nets.obs_encoder(params["obs_enc"], arch, obs + sign * fed)
    if name == "final_proposal":
        k = jnp.concatenate([k, nets.mlp(params["act_enc"], action, final_selu=True)], -1)
    h, c = nets.lstm_cell(params["lstm"], nets.LSTMState(h, c), k)
    d = nets.mlp(params["fc"], h, final_selu=True)
    out = {}
    if name == "final_proposal":
        o, a = arch.obs_code, arch.obs_code + arch.action_code
        out["action"] = jax.nn.sigmoid(nets.mlp(params["act_dec"], d[:, o:a], final_selu=False))
        out["reward"] = nets.mlp(params["reward_head"], d[:, a:], final_selu=False)[:, 0]
        d = d[:, :o]
    out["logits"] = nets.obs_decoder_logits(params["obs_dec"], arch, d)
    return h, c, jax.nn.sigmoid(out["logits"]), out


def _closed_loop_by_hand(name, params, xs, sign):
    """The closed loop run one stream and one step at a time; at an episode start (and at
    t = 0) the LSTM state and the fed-back õ are zero. Outputs `[T, B, ...]`."""
    T, B = xs.is_first.shape
    zeros = (jnp.zeros((1, ARCH.lstm_size)), jnp.zeros((1, ARCH.lstm_size)),
             jnp.zeros((1, ARCH.image_size, ARCH.image_size)))
    outs = [[None] * B for _ in range(T)]
    for b in range(B):
        h, c, fed = zeros
        for t in range(T):
            if bool(xs.is_first[t, b]):
                h, c, fed = zeros
            h, c, fed, outs[t][b] = _closed_loop_step_by_hand(
                name, params, h, c, fed, xs.obs[t, b:b + 1], xs.action[t, b:b + 1], sign)
    return {key: np.stack([np.concatenate([np.asarray(outs[t][b][key]) for b in range(B)]) for t in range(T)])
            for key in outs[0][0]}


@pytest.mark.parametrize("name", sorted(CLOSED_LOOP_SIGNS))
def test_closed_loop_unroll_equals_the_data_flow_by_hand(name):
    """For the closed loops `unroll` is itself a scan of `step`, so the test above compares a
    scan with a loop of the same step. Here both are pinned against the data flow written out
    with the networks: 3 steps of 2 streams; stream 1 starts a new episode at t = 2."""
    v = make_variant(name, ARCH)
    params = v.init(jax.random.PRNGKey(8))
    rng = np.random.default_rng(8)
    is_first = np.array([[True, True], [False, False], [False, True]])
    xs = StepInput(obs=jnp.asarray(rng.uniform(size=(3, 2, ARCH.image_size, ARCH.image_size)), jnp.float32),
                   action=jnp.asarray(rng.uniform(size=(3, 2, 3)), jnp.float32), is_first=jnp.asarray(is_first))
    want = _closed_loop_by_hand(name, params, xs, CLOSED_LOOP_SIGNS[name])
    _, got = jax.jit(v.unroll)(params, v.init_carry(2), xs)
    np.testing.assert_allclose(got["logits"], want["logits"], rtol=1e-5, atol=1e-5)
    if name == "final_proposal":
        np.testing.assert_allclose(got["action"], want["action"], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(got["reward"], want["reward"], rtol=1e-5, atol=1e-6)
    # The example can tell the feedback apart: without it the logits agree only where õ is 0
    # (the first step, and stream 1's new episode at t = 2).
    open_loop = _closed_loop_by_hand(name, params, xs, 0.0)["logits"]
    gap = np.abs(open_loop - want["logits"]).max(axis=(2, 3))
    assert gap[0].max() == 0 and gap[2, 1] == 0
    assert gap[1].min() > 1e-4 and gap[2, 0] > 1e-4, gap


def _check_loss_grads(v, weights, frozen=()):
    """check_grads of the weighted chunk loss w.r.t. every parameter group but `frozen`.

    Finite differences cannot see a stop-gradient, so a term that stops gradients into a
    group is checked with that group frozen."""
    with jax.enable_x64(True):
        params = jax.tree.map(lambda p: p.astype(jnp.float64), v.init(jax.random.PRNGKey(2)))
        fixed = {k: params.pop(k) for k in frozen}
        xs = _inputs(T=4, dtype=jnp.float64)
        next_obs = jnp.roll(xs.obs, -1, axis=0)

        @jax.jit
        def loss(p):
            carry = jax.tree.map(lambda c: c.astype(jnp.float64), v.init_carry(2))
            full = {**p, **fixed}
            _, outs = v.unroll(full, carry, xs)
            terms = v.loss_terms(full, xs, outs, next_obs, xs.action[..., 0])
            return sum(weights[k] * terms[k] for k in weights)

        check_grads(loss, (params,), order=1, modes=["rev"], eps=1e-6, atol=1e-5, rtol=1e-3)


@pytest.mark.parametrize("name", [n for n in NAMES if n != "baseline_recurrent"])
def test_gradients_pass_check_grads(name):
    """Reverse-mode gradients of the loss against finite differences (float64)."""
    v = make_variant(name, ARCH)
    _check_loss_grads(v, {k: 1.0 for k in v.default_loss_weights()})


def test_recurrent_baseline_gradients_pass_check_grads():
    v = make_variant("baseline_recurrent", ARCH)
    _check_loss_grads(v, {"recon_bce": 1.0})
    _check_loss_grads(v, {"code_mse": 1.0, "obs_bce": 1.0, "code_pred_mse": 1.0}, frozen=("obs_enc",))


def test_episode_start_resets_only_its_stream():
    v = make_variant("closed_loop_minus", ARCH)
    params = v.init(jax.random.PRNGKey(3))
    xs = _inputs()
    _, outs = v.unroll(params, v.init_carry(2), xs)
    # Stream 1 restarted at t=3: equal to a fresh run over its steps 3.. alone.
    tail = jax.tree.map(lambda a: a[3:, 1:2], xs)
    _, fresh = v.unroll(params, v.init_carry(1), tail)
    np.testing.assert_allclose(outs["logits"][3:, 1], fresh["logits"][:, 0], rtol=1e-5, atol=1e-6)
    # Stream 0 did not restart: its steps 3.. differ from a fresh start there.
    head = jax.tree.map(lambda a: a[3:, 0:1], xs)
    head = head.replace(is_first=jnp.ones_like(head.is_first))
    _, other = v.unroll(params, v.init_carry(1), head)
    assert float(jnp.max(jnp.abs(outs["logits"][3, 0] - other["logits"][0, 0]))) > 1e-4


@pytest.mark.parametrize("name", ["closed_loop_plus", "closed_loop_minus"])
def test_closed_loop_backpropagates_through_the_fed_back_prediction(name):
    """The loss at t=1 depends on the decoder through õ_1 fed back into the input; cutting
    that path with a stop-gradient changes the decoder's gradient."""
    v = make_variant(name, ARCH)
    params = v.init(jax.random.PRNGKey(4))
    xs = _inputs(T=2)

    def loss(p, cut):
        carry = v.init_carry(2)
        carry, _ = v.step(p, carry, jax.tree.map(lambda a: a[0], xs))
        if cut:
            carry = {**carry, "pred_obs": jax.lax.stop_gradient(carry["pred_obs"])}
        _, out = v.step(p, carry, jax.tree.map(lambda a: a[1], xs))
        return jnp.mean(out["logits"])

    g_full = jax.grad(loss)(params, False)["obs_dec"]["deconv0"]["kernel"]
    g_cut = jax.grad(loss)(params, True)["obs_dec"]["deconv0"]["kernel"]
    assert float(jnp.max(jnp.abs(g_full - g_cut))) > 1e-6


def test_residual_adds_the_input_code():
    v = make_variant("residual", ARCH)
    params = v.init(jax.random.PRNGKey(5))
    _, outs = v.unroll(params, v.init_carry(2), _inputs())
    base = make_variant("main", ARCH)
    _, plain = base.unroll(params, base.init_carry(2), _inputs())
    np.testing.assert_allclose(outs["pred_code"], plain["pred_code"] + outs["code"], rtol=1e-5, atol=1e-6)


def test_recurrent_baseline_stages_route_gradients_apart():
    """Stage 1 (recon) moves only the autoencoder, stage 2 (code MSE) only the LSTM+FC."""
    v = make_variant("baseline_recurrent", ARCH)
    params = v.init(jax.random.PRNGKey(6))
    xs = _inputs()
    nxt = jnp.roll(xs.obs, -1, axis=0)

    def grads(term):
        def loss(p):
            _, outs = v.unroll(p, v.init_carry(2), xs)
            return v.loss_terms(p, xs, outs, nxt, xs.action[..., 0])[term]
        g = jax.grad(loss)(params)
        return {k: float(sum(jnp.sum(jnp.abs(x)) for x in jax.tree.leaves(g[k]))) for k in g}

    recon, code = grads("recon_bce"), grads("code_mse")
    assert recon["obs_enc"] > 0 and recon["obs_dec"] > 0 and recon["lstm"] == 0 and recon["fc"] == 0
    assert code["lstm"] > 0 and code["fc"] > 0 and code["obs_enc"] == 0 and code["obs_dec"] == 0
    assert [w["recon_bce"] for w in v.stage_loss_weights()] == [1.0, 0.0]


def test_action_variant_sees_the_action():
    v = make_variant("main_action", ARCH)
    params = v.init(jax.random.PRNGKey(7))
    xs = _inputs()
    _, a = v.unroll(params, v.init_carry(2), xs)
    _, b = v.unroll(params, v.init_carry(2), xs.replace(action=1 - xs.action))
    assert float(jnp.max(jnp.abs(a["logits"] - b["logits"]))) > 1e-5
    m = make_variant("main", ARCH)
    mp = m.init(jax.random.PRNGKey(7))
    _, c = m.unroll(mp, m.init_carry(2), xs)
    _, d = m.unroll(mp, m.init_carry(2), xs.replace(action=1 - xs.action))
    np.testing.assert_array_equal(c["logits"], d["logits"])


def test_unknown_variant_and_loss_term_are_named():
    with pytest.raises(ValueError, match="unknown variant 'mian'"):
        make_variant("mian", ARCH)
    v = make_variant("main", ARCH)
    with pytest.raises(ValueError, match="unknown loss term 'reward'"):
        HParams.create(v, loss_weights={"reward": 1.0})
