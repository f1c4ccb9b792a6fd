"""Held-out evaluation: the batched path against one episode at a time and against a direct
computation, and the excess ratio."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdrl.data.episode import Episode
from cdrl.data.synthetic import synthetic_episodes
from cdrl.data.frames import COPY_EPS, pixel_bce
from cdrl.evaluation.metrics import evaluate, excess_ratio
from cdrl.models import TINY, StepInput, make_variant
from cdrl.models.base import bce_with_logits


def _episodes():
    eps = synthetic_episodes(5, 40, TINY.image_size, seed=3)
    return [Episode(e.frames[:n], e.actions[:n], e.rewards[:n]) for e, n in zip(eps, [40, 17, 33, 2, 25])]


@pytest.mark.parametrize("name", ["main", "residual_error", "closed_loop_minus"])
def test_batched_evaluation_equals_one_episode_at_a_time(name):
    """Episodes of different lengths side by side (padding masked, carries independent) give
    the per-episode path's numbers, transition-weighted."""
    v = make_variant(name, TINY)
    params = v.init(jax.random.PRNGKey(1))
    eps = _episodes()
    batched = evaluate(v, params, eps, unroll=8, batch=3)
    singles = [evaluate(v, params, [ep], unroll=8, batch=1) for ep in eps]
    weights = np.array([len(ep) - 1 for ep in eps], np.float64)
    for key in ("bce", "copy_bce", "target_entropy"):
        want = np.sum([s[key] * w for s, w in zip(singles, weights)]) / weights.sum()
        assert batched[key] == pytest.approx(want, rel=1e-5), key
    assert set(batched) >= {"bce", "copy_bce", "target_entropy", "excess_ratio"}
    assert ("code_pred_mse" in batched) == v.shared_code_space


def test_evaluation_equals_a_direct_computation():
    """One episode, one chunk: the mean per-pixel BCE of the model's logits, the clipped copy of
    the last frame, the targets' entropy, and the ratio of their gaps."""
    v = make_variant("main", TINY)
    params = v.init(jax.random.PRNGKey(2))
    ep = _episodes()[0]
    n = len(ep) - 1
    got = evaluate(v, params, [ep], unroll=n)
    obs = ep.frames[:-1].astype(np.float64) / 255
    target = ep.frames[1:].astype(np.float64) / 255
    xs = StepInput(obs=jnp.asarray(obs[:, None], jnp.float32), action=jnp.asarray(ep.actions[:-1, None]),
                   is_first=jnp.arange(n)[:, None] == 0)
    _, outs = jax.jit(v.unroll)(params, v.init_carry(1), xs)
    logits = np.asarray(outs["logits"][:, 0], np.float64)
    bce = np.mean(np.logaddexp(0, logits) - target * logits)
    copy = np.clip(obs, COPY_EPS, 1 - COPY_EPS)
    copy_bce = np.mean(-(target * np.log(copy) + (1 - target) * np.log(1 - copy)))
    p = np.clip(target, 1e-7, 1 - 1e-7)
    floor = np.mean(-(p * np.log(p) + (1 - p) * np.log(1 - p)))
    assert got["bce"] == pytest.approx(bce, rel=1e-5)
    assert got["copy_bce"] == pytest.approx(copy_bce, rel=1e-5)
    assert got["target_entropy"] == pytest.approx(floor, rel=1e-5)
    assert got["excess_ratio"] == pytest.approx((bce - floor) / (copy_bce - floor), rel=1e-4)


def test_the_training_loss_and_the_per_frame_score_are_one_bce():
    """`bce_with_logits` (the loss: the mean over everything) is the mean of `pixel_bce` (the
    score: a mean per frame), and both are the binary cross-entropy of sigmoid(logits), also
    where the logits saturate."""
    rng = np.random.default_rng(0)
    logits = rng.normal(0, 3, (4, 3, 16, 16)).astype(np.float32)
    logits[0, 0, :2] = [[-40.0] * 16, [40.0] * 16]
    target = rng.uniform(0, 1, logits.shape).astype(np.float32)
    l, t = logits.astype(np.float64), target.astype(np.float64)
    exact = np.logaddexp(0, l) - t * l  # -t log p - (1 - t) log(1 - p), p = sigmoid(l)
    per_frame = np.asarray(pixel_bce(jnp.asarray(logits), jnp.asarray(target)))
    loss = float(bce_with_logits(jnp.asarray(logits), jnp.asarray(target)))
    assert per_frame.shape == (4, 3)
    np.testing.assert_allclose(per_frame, exact.mean(axis=(-2, -1)), rtol=1e-6)
    assert loss == pytest.approx(exact.mean(), rel=1e-6)
    assert loss == pytest.approx(float(np.mean(per_frame, dtype=np.float64)), rel=1e-6)
    p = 1 / (1 + np.exp(-l[1:]))
    np.testing.assert_allclose(exact[1:], -(t[1:] * np.log(p) + (1 - t[1:]) * np.log1p(-p)), rtol=1e-9, atol=1e-12)


def test_excess_ratio_reads_as_documented():
    assert excess_ratio(0.48, 0.48, 0.47) == pytest.approx(1.0)  # as good as copying
    assert excess_ratio(0.47, 0.48, 0.47) == 0.0  # at the floor
    assert excess_ratio(0.475, 0.48, 0.47) == pytest.approx(0.5)
    assert np.isnan(excess_ratio(0.5, 0.47, 0.47))  # copying already at the floor: undefined
    with pytest.raises(ValueError, match="no episodes"):
        evaluate(make_variant("main", TINY), None, [])


@pytest.mark.parametrize("name", ["main", "closed_loop_minus", "final_proposal"])
def test_open_loop_scores_equal_a_step_by_step_computation(name):
    """Each window: C real frames from a zero carry, then the model's own sigmoid prediction fed
    back one Python step at a time (the recorded actions in); per horizon step the mean BCE, the
    copy of the last real frame, the floor and their ratio. Step 1 is the ordinary one-step
    prediction; closed loop − sees a zero error once it is fed its own prediction."""
    from cdrl.evaluation.multistep import multistep_scores, windows

    v = make_variant(name, TINY)
    params = v.init(jax.random.PRNGKey(4))
    eps = synthetic_episodes(2, 25, TINY.image_size, seed=3)
    context, horizon = 3, 4
    got = multistep_scores(v, params, eps, context, horizon, batch=3)  # 6 windows: two groups of 3
    spans = windows(eps, context + horizon)
    assert got["windows"] == len(spans) == 6
    step = jax.jit(v.step)
    sums = np.zeros((3, horizon))
    for i, s in spans:
        frames = eps[i].frames[s: s + context + horizon].astype(np.float64) / 255
        actions = eps[i].actions[s: s + context + horizon].astype(np.float32)
        carry, obs = v.init_carry(1), frames[0]
        for t in range(context + horizon - 1):
            x = StepInput(obs=jnp.asarray(obs[None], jnp.float32), action=jnp.asarray(actions[t][None]),
                          is_first=jnp.array([t == 0]))
            if name == "closed_loop_minus" and t >= context:  # its input o_t − õ_t is zero
                assert np.abs(np.asarray(x.obs) - np.asarray(carry["pred_obs"])).max() < 1e-6
            carry, out = step(params, carry, x)
            logits = np.asarray(out["logits"][0], np.float64)
            obs = frames[t + 1] if t + 1 < context else 1 / (1 + np.exp(-logits))
            if t >= context - 1:
                k, target = t - context + 1, frames[t + 1]
                last = np.clip(frames[context - 1], COPY_EPS, 1 - COPY_EPS)
                p = np.clip(target, 1e-7, 1 - 1e-7)
                sums[:, k] += [np.mean(np.logaddexp(0, logits) - target * logits),
                               np.mean(-(target * np.log(last) + (1 - target) * np.log(1 - last))),
                               np.mean(-(p * np.log(p) + (1 - p) * np.log(1 - p)))]
    bce, copy, floor = sums / len(spans)
    np.testing.assert_allclose(got["bce"], bce, rtol=1e-5)
    np.testing.assert_allclose(got["copy_bce"], copy, rtol=1e-5)
    np.testing.assert_allclose(got["target_entropy"], floor, rtol=1e-5)
    np.testing.assert_allclose(got["excess_ratio"], (bce - floor) / (copy - floor), rtol=1e-3)
    with pytest.raises(ValueError, match="context \\+ horizon = 30 frames"):
        multistep_scores(v, params, eps, 10, 20)
