"""Multi-step training: the model fed its own predictions between real frames
(`Variant.unroll_fed`, `HParams.feed_every`), against the one-step unroll and a step-by-step
computation; the curriculum's schedule and the option's checks."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdrl.data.stream import ChunkStream
from cdrl.data.synthetic import synthetic_episodes
from cdrl.models import TINY, StepInput, make_variant
from cdrl.models.base import bce_with_logits
from cdrl.runs.config import RunConfig
from cdrl.training.loop import TrainJob, feed_schedule
from cdrl.training.optim import HParams
from cdrl.training.step import chunk_loss, init_state


def _chunk(batch=2, T=7):
    eps = synthetic_episodes(3, 12, TINY.image_size, seed=5)
    return ChunkStream(eps, batch, T, image_size=TINY.image_size).next_chunk()


@pytest.mark.parametrize("name", ["main", "residual", "closed_loop_minus"])
def test_fed_unroll_with_every_frame_observed_is_the_one_step_unroll(name):
    """Observing every step, the fed-back path (a scan of single steps) gives the outputs and
    final carry of the variant's own unroll (for the open loops: the whole chunk encoded at once)."""
    v = make_variant(name, TINY)
    params = v.init(jax.random.PRNGKey(0))
    c = _chunk()
    xs = StepInput(obs=c.obs.astype(jnp.float32) / 255, action=c.action.astype(jnp.float32), is_first=c.is_first)
    carry0 = v.init_carry(2)
    want_carry, want = v.unroll(params, carry0, xs)
    got_carry, got = v.unroll_fed(params, carry0, xs, jnp.ones(c.is_first.shape, bool))
    np.testing.assert_allclose(got["logits"], want["logits"], rtol=2e-4, atol=2e-4)
    for a, b in zip(jax.tree.leaves(got_carry), jax.tree.leaves(want_carry)):
        np.testing.assert_allclose(a, b, rtol=2e-4, atol=2e-4)


@pytest.mark.parametrize("name", ["main", "closed_loop_minus"])
def test_multistep_loss_and_gradient_equal_a_step_by_step_computation(name):
    """feed_every K = 3 on a 7-step chunk: steps 0, 3, 6 (and episode starts) see the real
    frame, the others the sigmoid of the step before's prediction; the loss is the mean BCE of
    every step's prediction against the real next frame, and its gradient flows through the
    fed-back predictions (a Python loop of `step` differentiated as a whole)."""
    v = make_variant(name, TINY)
    params = v.init(jax.random.PRNGKey(1))
    c = _chunk()
    hp = HParams.create(v, feed_every=3)
    assert hp.fed

    def by_hand(p):
        carry, prev, total = v.init_carry(2), None, 0.0
        obs = c.obs.astype(jnp.float32) / 255
        for t in range(obs.shape[0]):
            seen = (t % 3 == 0) | c.is_first[t]
            o = obs[t] if prev is None else jnp.where(seen[:, None, None], obs[t], jax.nn.sigmoid(prev))
            carry, out = v.step(p, carry, StepInput(obs=o, action=c.action[t].astype(jnp.float32),
                                                    is_first=c.is_first[t]))
            prev = out["logits"]
            total = total + bce_with_logits(prev, c.next_obs[t].astype(jnp.float32) / 255)
        return total / obs.shape[0]

    want, want_g = jax.value_and_grad(by_hand)(params)
    (got, _), got_g = jax.value_and_grad(lambda p: chunk_loss(v, p, v.init_carry(2), hp, c), has_aux=True)(params)
    np.testing.assert_allclose(got, want, rtol=1e-5)
    for a, b in zip(jax.tree.leaves(got_g), jax.tree.leaves(want_g)):
        np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-6)
    one_step, _ = chunk_loss(v, params, v.init_carry(2), HParams.create(v), c)
    assert abs(float(got) - float(one_step)) > 1e-4  # the fed-back steps change the loss


def test_the_curriculum_sets_k_per_part_of_the_run_and_on_resume():
    """1,3,5 over 90 steps: K 1 from step 0, 3 from 30, 5 from 60; a run resumed at step 70
    takes 5; K is traced, so the program is the same (`fed` is set from the start)."""
    assert feed_schedule((1,), 90) == []
    assert feed_schedule((1, 3, 5), 90) == [(0, 1), (30, 3), (60, 5)]
    cfg = RunConfig(variant="main", preset="tiny", multistep="1,3,5", steps=90)
    v = make_variant("main", TINY)
    hp = cfg.hparams(v)
    assert hp.fed and int(hp.feed_every) == 1
    stream = ChunkStream(synthetic_episodes(2, 12, TINY.image_size), 1, 4, image_size=TINY.image_size)
    state = init_state(v, jax.random.PRNGKey(0), 1, hp)
    job = TrainJob(v, stream, hp, 90, [], curriculum=cfg.feed_curriculum)
    seen = {}
    for step in range(90):
        job.stage(step, state, resumed=False)
        seen[step] = int(job.hp.feed_every)
    assert (seen[0], seen[29], seen[30], seen[59], seen[60], seen[89]) == (1, 1, 3, 3, 5, 5)
    resumed = TrainJob(v, stream, hp, 90, [], curriculum=cfg.feed_curriculum)
    resumed.stage(70, state, resumed=True)
    assert int(resumed.hp.feed_every) == 5


def test_the_multistep_option_is_checked():
    for bad in ("0", "1,x", "", "2,-1"):
        with pytest.raises(ValueError, match="multistep must be K or K1,K2"):
            RunConfig(variant="main", multistep=bad)
    with pytest.raises(ValueError, match="multistep '3' is for offline runs"):
        RunConfig(variant="final_proposal", controller="critic", multistep="3")
    assert not RunConfig(variant="main").hparams(make_variant("main", TINY)).fed
    assert dataclasses.replace(RunConfig(variant="main"), multistep="4").feed_curriculum == (4,)
