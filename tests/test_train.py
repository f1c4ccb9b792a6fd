"""Truncated BPTT, the optimiser, the divergence monitor and the chunk streams."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdrl.data.episode import Episode
from cdrl.data.stream import ChunkStream
from cdrl.data.synthetic import synthetic_episodes
from cdrl.evaluation.metrics import evaluate
from cdrl.models import make_variant
from cdrl.models.arch import SMALL, TINY
from cdrl.training.loop import DivergenceError, fit
from cdrl.training.monitor import leaf_ratio
from cdrl.training.optim import HParams
from cdrl.training.step import chunk_loss, init_state, ratio_names, train_step, train_step_fn

ARCH = TINY


def _setup(name="main", batch=2, T=5, episodes=None, lr=0.1, seed=0):
    v = make_variant(name, ARCH)
    episodes = episodes or synthetic_episodes(3, 12, ARCH.image_size, seed=seed)
    stream = ChunkStream(episodes, batch, T, image_size=ARCH.image_size)
    hp = HParams.create(v, lr=lr)
    state = init_state(v, jax.random.PRNGKey(seed), batch, hp)
    return v, stream, hp, state


step_no_donate = jax.jit(train_step_fn, static_argnums=0)


def test_tbptt_cut_no_gradient_across_chunks_but_carry_flows():
    v, stream, hp, state = _setup("closed_loop_minus")
    c1, c2 = stream.next_chunk(), stream.next_chunk()

    def chunk2_loss(obs1):
        chunk1 = c1.replace(obs=obs1)
        _, (carry, _, _) = chunk_loss(v, state.params, state.carry, hp, chunk1)
        loss, _ = chunk_loss(v, state.params, carry, hp, c2)
        return loss

    obs1 = jnp.asarray(c1.obs, jnp.float32) / 255
    grad = jax.jit(jax.grad(chunk2_loss))(obs1)
    assert float(jnp.max(jnp.abs(grad))) == 0.0
    # ...while the value of chunk 2's loss does depend on chunk 1 through the carry.
    value = jax.jit(chunk2_loss)
    assert abs(float(value(obs1)) - float(value(1 - obs1))) > 1e-6


def test_second_chunk_does_not_recompile():
    v, stream, hp, state = _setup()
    state, _ = train_step(v, state, hp, stream.next_chunk())
    before = train_step._cache_size()
    for lr in (0.05, 0.01):  # new hyper-parameter values are traced, not static
        hp2 = HParams.create(v, lr=lr)
        state, _ = train_step(v, state, hp2, stream.next_chunk())
    assert train_step._cache_size() == before


def test_sgd_momentum_is_the_thesis_rule():
    """mu <- beta mu + g; w <- w - alpha mu, over two steps."""
    v, stream, hp, state = _setup(lr=0.05)
    hp = HParams.create(v, lr=0.05, momentum=0.9)
    chunks = [stream.next_chunk(), stream.next_chunk()]
    w, carry, mu = state.params, state.carry, None
    grad = jax.jit(jax.value_and_grad(lambda p, c, ch: chunk_loss(v, p, c, hp, ch), has_aux=True))
    for chunk in chunks:
        (_, (carry_next, _, _)), g = grad(w, carry, chunk)
        mu = g if mu is None else jax.tree.map(lambda m, gi: 0.9 * m + gi, mu, g)
        w = jax.tree.map(lambda p, m: p - 0.05 * m, w, mu)
        carry = carry_next
    for chunk in chunks:
        state, _ = step_no_donate(v, state, hp, chunk)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6), state.params, w)


def test_monitor_ratios_equal_direct_norms():
    v, stream, hp, state = _setup()
    state, _ = step_no_donate(v, state, hp, stream.next_chunk())  # biases become non-zero
    chunk = stream.next_chunk()
    grads = jax.grad(lambda p: chunk_loss(v, p, state.carry, hp, chunk)[0])(state.params)
    want = [np.linalg.norm(np.asarray(g)) / np.linalg.norm(np.asarray(p))
            for g, p in zip(jax.tree.leaves(grads), jax.tree.leaves(state.params))]
    _, metrics = step_no_donate(v, state, hp, chunk)
    np.testing.assert_allclose(metrics["ratios"], want, rtol=1e-4)
    names = ratio_names(state)
    assert len(names) == len(want) and "obs_enc/conv0/kernel" in names
    kernels = [w for w, p in zip(want, jax.tree.leaves(state.params)) if p.ndim >= 2]
    assert float(metrics["max_ratio"]) == pytest.approx(max(kernels), rel=1e-4)
    assert float(leaf_ratio(jnp.ones(3), jnp.zeros(3))) == 0.0  # a zero group reports 0


def test_small_learning_rate_is_not_taken_for_divergence():
    """After the first update a zero-initialised bias has norm lr * |g|, so its ratio is about
    1 / lr: the check watches kernels only, or every small rate would 'diverge' at step 1."""
    v, stream, _, state = _setup(lr=1e-4)
    hp = HParams.create(v, lr=1e-4, diverge_threshold=1e3)
    for _ in range(3):
        state, metrics = step_no_donate(v, state, hp, stream.next_chunk())
        assert not bool(metrics["diverged"])
    biases = [r for r, n in zip(metrics["ratios"], ratio_names(state)) if n.endswith("bias")]
    assert max(biases) > 1e3  # logged, and above the threshold, but not watched


def test_monitor_state_has_fixed_structure_under_scan():
    v, stream, hp, state = _setup()
    chunks = jax.tree.map(lambda *a: jnp.stack(a), *[stream.next_chunk() for _ in range(3)])
    final, metrics = jax.lax.scan(lambda s, c: train_step_fn(v, s, hp, c), state, chunks)
    assert metrics["ratios"].shape == (3, len(jax.tree.leaves(state.params)))
    assert int(final.step) == 3


def test_large_learning_rate_stops_with_the_group_named_and_keeps_good_params():
    v, stream, _, state = _setup(lr=1e3)
    hp = HParams.create(v, lr=1e3, diverge_threshold=1e3)
    seen = []
    with pytest.raises(DivergenceError, match=r"diverged at step \d+: .*worst parameter group: [a-z_]+/") as err:
        fit(v, stream, 50, hp, state=state,
                 callback=lambda r: seen.append(r))
    e = err.value
    assert e.group in ratio_names(e.state)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(e.state.params))
    assert int(e.state.step) == e.step == len(seen)
    # The parameters are the good ones of the steps before the bad one: the same run stopped
    # just before it ends with the same parameters (not merely finite ones).
    _, stream2, _, state2 = _setup(lr=1e3)
    good, _ = fit(v, stream2, e.step, hp, state=state2)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-6, atol=0), e.state.params, good.params)


def test_nan_in_data_gives_a_clear_error():
    frames = np.random.default_rng(0).uniform(size=(5, 16, 16)).astype(np.float32)
    frames[2, 3, 4] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        Episode(frames, np.zeros((5, 3), np.float32), np.zeros(5, np.float32))
    # NaN that reaches the trainer anyway (a chunk built by hand) stops the run by name.
    v, stream, hp, state = _setup()
    chunk = stream.next_chunk()
    bad = chunk.replace(obs=np.where(np.arange(16) == 3, np.nan, chunk.obs / 255.0).astype(np.float32))

    class Once:
        batch, unroll = 2, 5

        def next_chunk(self):
            return bad

    with pytest.raises(DivergenceError, match="NaN/Inf"):
        fit(v, Once(), 1, hp, state=state)


def test_bad_input_errors_name_the_problem():
    eps = synthetic_episodes(2, 8, 16)
    with pytest.raises(ValueError, match="frames of 16x16, the model expects 64x64"):
        ChunkStream(eps, 1, 4, image_size=64).next_chunk()
    with pytest.raises(ValueError, match="unroll length T must be >= 1"):
        ChunkStream(eps, 1, 0)
    with pytest.raises(ValueError, match="batch size B must be >= 1"):
        ChunkStream(eps, 0, 4)
    with pytest.raises(ValueError, match=r"must lie in \[0, 1\]"):
        Episode(np.full((3, 16, 16), 1.5, np.float32), np.zeros((3, 3), np.float32), np.zeros(3, np.float32))
    with pytest.raises(ValueError, match=r"must be \[N, H, W\]"):
        Episode(np.zeros((3, 16, 16, 3), np.uint8), np.zeros((3, 3), np.float32), np.zeros(3, np.float32))


def test_chunks_are_aligned_and_mark_episode_starts():
    eps = [Episode(np.full((n, 16, 16), i, np.uint8), np.full((n, 3), 0.5, np.float32),
                   np.arange(n, dtype=np.float32)) for i, n in enumerate([4, 6, 3])]
    stream = ChunkStream(eps, 1, 4, shuffle=False)
    chunks = [stream.next_chunk() for _ in range(3)]
    obs = np.concatenate([c.obs[:, 0, 0, 0] for c in chunks])
    nxt = np.concatenate([c.next_obs[:, 0, 0, 0] for c in chunks])
    first = np.concatenate([c.is_first[:, 0] for c in chunks])
    reward = np.concatenate([c.reward[:, 0] for c in chunks])
    # 3 + 5 + 2 transitions, then the epoch wraps around.
    np.testing.assert_array_equal(obs[:10], [0, 0, 0, 1, 1, 1, 1, 1, 2, 2])
    np.testing.assert_array_equal(nxt[:10], obs[:10])  # never pairs frames of two episodes
    np.testing.assert_array_equal(first[:10], [1, 0, 0, 1, 0, 0, 0, 0, 1, 0])
    np.testing.assert_array_equal(reward[:3], [1, 2, 3])  # r_{t+1}
    assert first[10]
    assert not np.concatenate([c.truncated[:, 0] for c in chunks]).any()  # no step limit: every end is the game's
    # a step limit of 5: the 5-step episode ended at it (its last step is marked), the others in the game
    limited = ChunkStream(eps, 1, 4, shuffle=False, step_limit=5)
    truncated = np.concatenate([limited.next_chunk().truncated[:, 0] for _ in range(3)])
    np.testing.assert_array_equal(truncated[:10], [0, 0, 0, 0, 0, 0, 0, 1, 0, 0])


def test_stream_cursor_resumes_exactly():
    eps = synthetic_episodes(5, 9, 16, seed=3)
    a = ChunkStream(eps, 2, 4, seed=7)
    for _ in range(4):
        a.next_chunk()
    b = ChunkStream(eps, 2, 4, seed=7)
    b.load_state_dict(a.state_dict())
    for _ in range(6):
        ca, cb = a.next_chunk(), b.next_chunk()
        np.testing.assert_array_equal(ca.obs, cb.obs)
        np.testing.assert_array_equal(ca.is_first, cb.is_first)


def test_jit_equals_no_jit():
    v, stream, hp, state = _setup("residual_error", batch=1, T=2)
    chunk = stream.next_chunk()
    jitted, m1 = step_no_donate(v, state, hp, chunk)
    with jax.disable_jit():
        plain, m2 = train_step_fn(v, state, hp, chunk)
    np.testing.assert_allclose(m1["loss"], m2["loss"], rtol=1e-5)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6), jitted.params, plain.params)


def test_vmap_over_two_learning_rates_equals_two_runs():
    v, stream, _, state = _setup()
    chunk = stream.next_chunk()
    hps = [HParams.create(v, lr=lr) for lr in (0.1, 0.02)]
    both = jax.tree.map(lambda *a: jnp.stack(a), *hps)
    states = jax.tree.map(lambda a: jnp.stack([a, a]), state)
    vm, _ = jax.jit(jax.vmap(train_step_fn, in_axes=(None, 0, 0, None)), static_argnums=0)(
        v, states, both, chunk)
    for i, hp in enumerate(hps):
        single, _ = step_no_donate(v, state, hp, chunk)
        jax.tree.map(lambda a, b: np.testing.assert_allclose(a[i], b, rtol=1e-5, atol=1e-6), vm.params, single.params)


@pytest.mark.default_opt
def test_main_learns_well_below_copy_last_frame():
    """The small preset of `main` on a learnable moving blob, held-out episodes."""
    arch = SMALL
    v = make_variant("main", arch)
    train_eps = synthetic_episodes(16, 64, arch.image_size, seed=0, pushed=False)
    test_eps = synthetic_episodes(2, 64, arch.image_size, seed=1, pushed=False)
    stream = ChunkStream(train_eps, 4, 16, image_size=arch.image_size)
    hp = HParams.create(v, lr=1.0, momentum=0.9)
    state, history = fit(v, stream, 240, hp, key=jax.random.PRNGKey(0))
    result = evaluate(v, state.params, test_eps, unroll=16)
    assert np.mean([h["loss"] for h in history[-20:]]) < 0.5 * np.mean([h["loss"] for h in history[:5]])
    assert result["bce"] < 0.85 * result["copy_bce"], result
