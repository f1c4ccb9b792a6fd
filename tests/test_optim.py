"""Optimisers through optax: traced hyper-parameters (one program for any values), the
schedules, clipping, Adam against its equations, the divergence check and exact resume for
an optimiser other than the thesis's SGD, and the run recipes."""
import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdrl.data.stream import ChunkStream
from cdrl.data.synthetic import synthetic_episodes
from cdrl.models import TINY, make_variant
from cdrl.runs.config import RECIPES, RunConfig, saved_config
from cdrl.runs.train import train_run
from cdrl.training.loop import DivergenceError, fit
from cdrl.training.optim import OPTIMIZERS, HParams, OptHParams
from cdrl.training.step import chunk_loss, init_state, train_step_fn
from cdrl.runs.config import upgrade

STEP = jax.jit(train_step_fn, static_argnums=0)


def _setup(opt: OptHParams, seed=0):
    v = make_variant("main", TINY)
    stream = ChunkStream(synthetic_episodes(3, 12, TINY.image_size, seed=seed), 2, 5, image_size=TINY.image_size)
    hp = HParams.create(v, opt=opt)
    return v, stream, hp, init_state(v, jax.random.PRNGKey(seed), 2, hp)


def _grads(v, hp, state, chunk):
    return jax.jit(jax.grad(lambda p: chunk_loss(v, p, state.carry, hp, chunk)[0]))(state.params)


@pytest.mark.parametrize("name", sorted(OPTIMIZERS))
def test_every_optimizer_trains_and_one_program_serves_any_numbers(name):
    v, stream, hp, state = _setup(OptHParams.create(name, lr=1e-3))
    chunk = stream.next_chunk()
    before = STEP._cache_size()
    new, m = STEP(v, state, hp, chunk)
    assert not bool(m["diverged"])
    assert any(not np.array_equal(a, b) for a, b in zip(jax.tree.leaves(new.params), jax.tree.leaves(state.params)))
    compiled = STEP._cache_size()
    # One program per optimiser (an earlier test file in this process may have compiled sgd's).
    assert compiled <= before + 1
    other = HParams.create(v, opt=OptHParams.create(name, lr=3e-4, momentum=0.5, b2=0.99, weight_decay=0.1,
                                                    grad_clip=1.0, warmup=10, decay_steps=100))
    STEP(v, state, other, chunk)
    assert STEP._cache_size() == compiled  # new values are traced, not a new program


def test_schedule_warmup_then_cosine():
    o = OptHParams.create(lr=2.0, warmup=4, decay_steps=10)
    lr = [float(o.learning_rate(jnp.int32(t))) for t in range(12)]
    np.testing.assert_allclose(lr[:3], [2.0 * 0.25 * 0.5 * (1 + np.cos(np.pi * t / 10)) * (t + 1) for t in range(3)],
                               rtol=1e-6)
    np.testing.assert_allclose(lr[5], 2.0 * 0.5 * (1 + np.cos(np.pi * 0.5)), rtol=1e-6)
    assert lr[10] == pytest.approx(0.0, abs=1e-7) and lr[11] == pytest.approx(0.0, abs=1e-7)
    constant = OptHParams.create(lr=0.3)
    assert all(float(constant.learning_rate(jnp.int32(t))) == pytest.approx(0.3) for t in (0, 7, 10_000))


def test_grad_clip_scales_the_step_to_the_largest_norm():
    """With clipping at c < ||g||, plain SGD (no momentum) moves by lr * g * c / ||g||; at 0 it
    is off and moves by lr * g."""
    v, stream, _, state = _setup(OptHParams.create(lr=0.1, momentum=0.0))
    chunk = stream.next_chunk()
    hp_free = HParams.create(v, opt=OptHParams.create(lr=0.1, momentum=0.0))
    g = _grads(v, hp_free, state, chunk)
    norm = float(jnp.sqrt(sum(jnp.sum(x ** 2) for x in jax.tree.leaves(g))))
    for clip, scale in ((0.0, 1.0), (norm / 4, 0.25)):
        hp = HParams.create(v, opt=OptHParams.create(lr=0.1, momentum=0.0, grad_clip=clip))
        new, _ = STEP(v, state, hp, chunk)
        jax.tree.map(lambda p1, p0, gi: np.testing.assert_allclose(p1, p0 - 0.1 * scale * gi, rtol=2e-4, atol=1e-7),
                     new.params, state.params, g)


def test_adam_is_adam_with_momentum_as_beta1():
    b1, b2, lr, eps = 0.8, 0.95, 1e-2, 1e-8
    v, stream, hp, state = _setup(OptHParams.create("adam", lr=lr, momentum=b1, b2=b2))
    chunks = [stream.next_chunk(), stream.next_chunk()]
    w, carry = state.params, state.carry
    m = jax.tree.map(jnp.zeros_like, w)
    s = jax.tree.map(jnp.zeros_like, w)
    grad = jax.jit(jax.value_and_grad(lambda p, c, ch: chunk_loss(v, p, c, hp, ch), has_aux=True))
    for t, chunk in enumerate(chunks, start=1):
        (_, (carry, _, _)), g = grad(w, carry, chunk)
        m = jax.tree.map(lambda a, gi: b1 * a + (1 - b1) * gi, m, g)
        s = jax.tree.map(lambda a, gi: b2 * a + (1 - b2) * gi * gi, s, g)
        w = jax.tree.map(lambda p, a, q: p - lr * (a / (1 - b1 ** t)) / (jnp.sqrt(q / (1 - b2 ** t)) + eps), w, m, s)
    for chunk in chunks:
        state, _ = STEP(v, state, hp, chunk)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6), state.params, w)


def test_divergence_check_works_for_adam():
    v, stream, hp, state = _setup(OptHParams.create("adam", lr=50.0))
    hp = hp.replace(diverge_threshold=jnp.float32(0.5))
    with pytest.raises(DivergenceError, match="worst parameter group: [a-z_]+/") as err:
        fit(v, stream, 30, hp, state=state)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(err.value.state.params))


RUN = dict(preset="tiny", data="synthetic", episodes=6, episode_steps=20, unroll=4, batch=2,
           eval_every=0, eval_episodes=1, checkpoint_every=3)


def _losses(run_dir):
    return [json.loads(line)["loss"] for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def test_resume_is_exact_for_adamw_with_warmup_cosine_and_clipping(tmp_path):
    opts = dict(optimizer="adamw", lr=3e-3, weight_decay=0.01, grad_clip=0.5, lr_schedule="cosine",
                lr_warmup=2, lr_decay_steps=6, **RUN)
    train_run(RunConfig(steps=6, **opts), tmp_path / "full", progress=False)
    train_run(RunConfig(steps=3, **opts), tmp_path / "half", progress=False)
    train_run(None, tmp_path / "half", resume=True, overrides={"steps": 6}, progress=False)
    assert _losses(tmp_path / "half") == _losses(tmp_path / "full")
    saved = upgrade(json.loads((tmp_path / "half" / "config.json").read_text()))
    assert saved["optimizer"] == "adamw" and saved["lr_decay_steps"] == 6


def test_recipes_fill_only_what_the_run_does_not_set():
    thesis = RunConfig(recipe="thesis")
    assert (thesis.optimizer, thesis.lr, thesis.momentum, thesis.batch, thesis.unroll, thesis.obs_norm,
            thesis.fc_init_gain) == ("sgd", 0.1, 0.9, 1, 32, "none", 1.0)
    mixed = RunConfig(recipe="thesis", lr=0.3, batch=8)
    assert (mixed.lr, mixed.batch, mixed.momentum) == (0.3, 8, 0.9)
    fast = RunConfig()
    assert fast.recipe == "tuned" and all(getattr(fast, k) == v for k, v in RECIPES["tuned"].items())
    online = RunConfig(variant="final_proposal")
    assert (online.lr, online.batch, online.unroll, online.fc_init_gain, online.obs_norm) == (0.1, 8, 16, 1.0, "data")
    # A config.json from before recipes (no 'recipe', none of the new options) reads as the thesis's.
    old = {k: v for k, v in dataclasses.asdict(RunConfig(recipe="thesis")).items()
           if k not in RECIPES["thesis"] and k not in ("recipe", "level", "obs_mean", "obs_std", "lr_decay_steps")}
    assert saved_config({**old, "lr": 0.1, "momentum": 0.9, "batch": 1, "unroll": 32}) == RunConfig(recipe="thesis")
    assert RunConfig(lr_schedule="cosine", steps=700).lr_decay_steps == 700
    for bad, match in ((dict(recipe="quick"), "unknown recipe 'quick'"), (dict(optimizer="adagrad"), "optimizer must be one of"),
                       (dict(lr_schedule="step"), "lr_schedule must be one of"), (dict(obs_norm="batch"), "obs_norm must be"),
                       (dict(b2=1.0), "0 <= b2 < 1"), (dict(grad_clip=-1.0), "grad_clip must be >= 0"),
                       (dict(level="hard"), "level must be one of"), (dict(diverge_threshold=0.0), "diverge_threshold must be > 0"),
                       (dict(variant="mian"), "unknown variant 'mian'")):
        with pytest.raises(ValueError, match=match):
            RunConfig(**bad)
