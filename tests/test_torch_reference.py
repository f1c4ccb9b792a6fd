"""cdrl's JAX programs against the eager PyTorch reference (reference/torch_model.py):
same weights and data give the same loss, gradients, final carry and SGD-momentum updates.

`make test` runs this file compiled at XLA's default optimisation level (the `default_opt`
mark, tests/conftest.py): the programs users run.
"""

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.default_opt

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from cdrl.data.stream import Chunk  # noqa: E402
from cdrl.models import make_variant, nets  # noqa: E402
from cdrl.models.arch import THESIS, TINY  # noqa: E402
from cdrl.training.optim import HParams, make_optimizer  # noqa: E402
from cdrl.training.step import TrainState, chunk_loss, ratio_names, train_step_fn  # noqa: E402

from reference import torch_model as tr  # noqa: E402

VARIANTS = ("main", "closed_loop_minus")
_FAST_COMPILE = {"xla_backend_optimization_level": 0}


def _compiled(fn, *args):
    """`jax.jit(fn)` compiled for `args` (see the module docstring)."""
    return jax.jit(fn).lower(*args).compile(compiler_options=_FAST_COMPILE)


def _init(v, seed):
    key = jax.random.PRNGKey(seed)
    return _compiled(v.init, key)(key)


@pytest.fixture(autouse=True, scope="module")
def _deterministic_torch():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a fixed summation order; the tolerances do not rely on it
    yield
    torch.set_num_threads(threads)


def _chunk(arch, T, B, seed, reset=True):
    rng = np.random.default_rng(seed)
    s = arch.image_size
    frames = rng.random((T + 1, B, s, s), dtype=np.float32)
    is_first = np.zeros((T, B), bool)
    if reset:
        is_first[T // 2, B - 1] = True  # one stream starts a new episode mid-chunk
    return Chunk(
        obs=jnp.asarray(frames[:-1]),
        next_obs=jnp.asarray(frames[1:]),
        action=jnp.zeros((T, B, arch.action_dim)),
        reward=jnp.zeros((T, B)),
        is_first=jnp.asarray(is_first),
    )


def _carry(v, B, seed):
    """A non-zero incoming carry."""
    rng = np.random.default_rng(seed)
    H, s = v.arch.lstm_size, v.arch.image_size
    lstm = nets.LSTMState(jnp.asarray(rng.uniform(-0.9, 0.9, (B, H)), jnp.float32),
                          jnp.asarray(rng.normal(0, 1, (B, H)), jnp.float32))
    if v.name == "closed_loop_minus":
        return {"lstm": lstm, "pred_obs": jnp.asarray(rng.random((B, s, s)), jnp.float32)}
    return lstm


def _torch_inputs(chunk):
    t = lambda x: torch.from_numpy(np.array(x))  # noqa: E731
    return t(chunk.obs), t(chunk.next_obs), t(chunk.is_first)


def _cdrl_loss_grads(v, params, carry, chunk):
    hp = HParams.create(v)
    fn = _compiled(jax.value_and_grad(lambda p, c, ch: chunk_loss(v, p, c, hp, ch), has_aux=True),
                   params, carry, chunk)
    (loss, (carry_out, _, _)), grads = fn(params, carry, chunk)
    return float(loss), carry_out, grads


def _torch_loss_grads(v, params, carry, chunk):
    model = tr.load_cdrl_params(tr.TorchModel(v.arch, v.name), params)
    loss, carry_out = tr.chunk_loss(model, tr.carry_from_cdrl(carry), *_torch_inputs(chunk))
    loss.backward()
    return loss.item(), tr.carry_to_numpy(carry_out), tr.grads_as_cdrl(model)


def _flat_carry(carry):
    if isinstance(carry, dict):
        return (carry["lstm"].h, carry["lstm"].c, carry["pred_obs"])
    return (carry.h, carry.c)


def _assert_trees_close(ours, ref, rtol, atol_frac, what):
    """Leaf by leaf: |a - b| <= atol_frac * max|b| + rtol * |b| (atol relative to the leaf's scale)."""
    names = jax.tree_util.tree_flatten_with_path(ref)[0]
    ours_leaves = jax.tree.leaves(ours)
    assert len(ours_leaves) == len(names)
    for (path, b), a in zip(names, ours_leaves):
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape, (path, a.shape, b.shape)
        scale = float(np.max(np.abs(b)))
        assert scale > 0 or "bias" in jax.tree_util.keystr(path), f"{what} {jax.tree_util.keystr(path)} is all zero"
        np.testing.assert_allclose(a, b, rtol=rtol, atol=atol_frac * scale + 1e-12,
                                   err_msg=f"{what} {jax.tree_util.keystr(path)}")


def _compare(name, arch, T, B, rtol, atol_frac):
    v = make_variant(name, arch)
    params = _init(v, 0)
    chunk, carry = _chunk(arch, T, B, seed=1), _carry(v, B, seed=2)
    loss_j, carry_j, grads_j = _cdrl_loss_grads(v, params, carry, chunk)
    loss_t, carry_t, grads_t = _torch_loss_grads(v, params, carry, chunk)
    assert loss_j == pytest.approx(loss_t, rel=1e-5)
    _assert_trees_close(grads_t, jax.tree.map(np.asarray, grads_j), rtol, atol_frac, "gradient")
    for a, b in zip(carry_t, _flat_carry(carry_j)):
        np.testing.assert_allclose(a, np.asarray(b), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("name", VARIANTS)
def test_tiny_loss_grads_carry_match_torch(name):
    _compare(name, TINY, T=5, B=2, rtol=1e-5, atol_frac=1e-5)


def test_thesis_main_one_step_matches_torch():
    """The thesis-sized network (150x150 frames, LSTM 512): one T=2, B=1 chunk."""
    # Gradients here are ~1e-5..1e-6: atol is relative to each leaf's largest entry (seen: 5e-6).
    _compare("main", THESIS, T=2, B=1, rtol=1e-4, atol_frac=2e-5)


def test_sgd_momentum_steps_match_torch():
    """Two cdrl train steps (SGD lr 0.1, momentum 0.9; the carry flows from chunk to chunk)
    against two torch.optim.SGD steps: same loss, monitor ratios, parameters and carry after
    each (closed loop −: its carry holds the fed-back prediction too)."""
    name, arch, T, B = "closed_loop_minus", TINY, 5, 2
    v = make_variant(name, arch)
    hp = HParams.create(v, lr=0.1, momentum=0.9)
    params = _init(v, 3)
    state = TrainState(params=params, opt_state=make_optimizer(hp.opt).init(params),
                             carry=_carry(v, B, seed=4), step=jnp.zeros((), jnp.int32))
    model = tr.load_cdrl_params(tr.TorchModel(arch, name), state.params)
    opt = tr.make_optimizer(model, lr=0.1, momentum=0.9)
    carry_t = tr.carry_from_cdrl(state.carry)
    chunks = [_chunk(arch, T, B, seed=10 + i, reset=(i == 1)) for i in range(2)]
    step = _compiled(lambda s, h, c: train_step_fn(v, s, h, c), state, hp, chunks[0])
    for i, chunk in enumerate(chunks):
        state, metrics = step(state, hp, chunk)
        assert not bool(metrics["diverged"])
        loss_t, carry_t, ratios = tr.train_step(model, opt, carry_t, *_torch_inputs(chunk), monitor=True)
        assert float(metrics["loss"]) == pytest.approx(float(loss_t), rel=1e-5)
        # The monitor's ratios, in cdrl's leaf order.
        names = tr.param_names(model)
        order = [names.index(n) for n in ratio_names(state)]
        np.testing.assert_allclose(ratios.numpy()[order], np.asarray(metrics["ratios"]), rtol=1e-4, atol=1e-7)
        _assert_trees_close(tr.params_as_cdrl(model), jax.tree.map(np.asarray, state.params), 1e-5, 1e-6,
                            f"parameter after step {i + 1}")
        for a, b in zip(carry_t, _flat_carry(state.carry)):
            np.testing.assert_allclose(a, np.asarray(b), rtol=1e-5, atol=1e-6)


def test_load_rejects_other_trees():
    model = tr.TorchModel(TINY, "main")
    params = jax.eval_shape(make_variant("main_action", TINY).init, jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="act_enc"):
        tr.load_cdrl_params(model, params)
