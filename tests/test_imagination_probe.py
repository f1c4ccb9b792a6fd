"""experiments/control_probes/imagination_probe.py's scores against direct computations, and the
play its probes follow (`followed_play.py` beside it) against the model stepped by hand."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import games
from cdrl.data.frames import model_obs
from cdrl.models import make_variant
from cdrl.models.arch import TINY
from cdrl.models.base import StepInput
from envs.policies import privileged_policy
from experiments.control_probes import imagination_probe as ip
from experiments.control_probes.followed_play import follow_step, start


def _rewards(seed, starts=200, horizon=6):
    rng = np.random.default_rng(seed)
    return rng.choice([0.0, 0.5, -0.25], size=(starts, len(ip.SEQUENCES), horizon), p=[0.8, 0.1, 0.1])


def test_a_perfect_imagination_agrees_on_every_start_and_a_reversed_one_on_none():
    real = _rewards(0)
    got = ip.scores(real, real, [6])["6"]
    assert got["corr_all"] == pytest.approx(1.0)
    assert got["corr_steer"] == pytest.approx(1.0)
    assert got["best_steer_agree"] == 1.0
    assert got["accelerate_gap_imagined"] == pytest.approx(got["accelerate_gap_real"])
    flipped = ip.scores(real, -real, [6])["6"]
    assert flipped["corr_steer"] == pytest.approx(-1.0)
    assert flipped["best_steer_agree"] == 0.0  # the real best is the imagined worst


def test_scores_equal_a_direct_loop_over_the_starts():
    real, imagined = _rewards(1), _rewards(2)
    got = ip.scores(real, imagined, [1, 4])
    for k in (1, 4):
        r, i = real[..., :k].sum(-1), imagined[..., :k].sum(-1)
        agree, counted, dr, di, firsts = 0, 0, [], [], []
        for rs, is_ in zip(r, i):
            steer_r, steer_i = rs[:ip.STEER], is_[:ip.STEER]
            if np.sum(steer_r == steer_r.max()) != 1:
                continue  # no one best direction: the start is left out
            counted += 1
            agree += int(np.argmax(steer_i) == np.argmax(steer_r))
            firsts.append(int(np.argmax(steer_r)))
            dr += list(steer_r - steer_r.mean())
            di += list(steer_i - steer_i.mean())
        assert got[str(k)]["starts_with_one_best"] == counted
        assert got[str(k)]["best_steer_agree"] == pytest.approx(agree / counted)
        assert got[str(k)]["corr_steer"] == pytest.approx(np.corrcoef(dr, di)[0, 1])
        assert got[str(k)]["best_share_real"] == pytest.approx([firsts.count(j) / counted for j in range(ip.STEER)])
        assert got[str(k)]["corr_all"] == pytest.approx(np.corrcoef(r.ravel(), i.ravel())[0, 1])
        assert got[str(k)]["accelerate_gap_real"] == pytest.approx(np.mean(r[:, 3] - r[:, 0]))


def test_the_sequences_are_three_ways_to_steer_without_accelerating_then_one_that_accelerates():
    buttons = np.asarray(list(ip.SEQUENCES.values()))
    assert ip.STEER == 3 and buttons.shape == (4, 3)
    assert not buttons[:ip.STEER, 2].any() and buttons[ip.STEER, 2] == 1.0  # button 2: accelerate
    assert len({tuple(b) for b in buttons[:ip.STEER, :2]}) == 3


def test_the_followed_model_takes_the_frame_and_the_buttons_executed_there():
    """`followed_play`'s model state after step t equals the model stepped by hand on (o_t, a_t),
    a_t the buttons executed at o_t (with no exploration: the privileged policy's), as recorded
    data sets and acting controllers give them."""
    g, env_params = games.test_game()
    variant = make_variant("final_proposal", TINY)
    params = variant.init(jax.random.PRNGKey(0))
    body = follow_step(variant, params, g, env_params, 0.0)
    c0 = start(variant, g, env_params, jax.random.PRNGKey(3))
    h, label, alive, frames = jax.jit(lambda c: jax.lax.scan(body, c, None, length=8))(c0)[1]
    assert bool(alive.all())

    state, obs, carry, first, key, _, _ = c0
    privileged = privileged_policy(g)
    for t in range(8):
        key, k_policy, _, k_env = jax.random.split(key, 4)
        buttons, _ = privileged.step(k_policy, None, obs, state, env_params)
        np.testing.assert_array_equal(label[t], buttons)
        np.testing.assert_allclose(frames[t], model_obs(obs, variant.arch), atol=1e-6)
        carry, _ = variant.step(params, carry, StepInput(obs=model_obs(obs, variant.arch)[None],
                                                         action=buttons[None], is_first=jnp.array([t == 0])))
        np.testing.assert_allclose(h[t], variant.features(carry)[0], rtol=1e-5, atol=1e-5)
        obs, state, *_ = g.step(k_env, state, buttons, env_params)
