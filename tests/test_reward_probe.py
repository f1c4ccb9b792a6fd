"""experiments/control_probes/reward_probe.py's targets and scores, against direct computations."""

import numpy as np

from experiments.control_probes import reward_probe as rp


def test_pellets_ahead_sums_the_discounted_positive_rewards_of_the_episode():
    rng = np.random.default_rng(0)
    rewards = rng.choice([0.0, 0.5, -0.25], size=30, p=[0.6, 0.2, 0.2]).astype(np.float32)
    rewards[0] = 0.0  # r_0: nothing is received on arriving at the first frame
    n = len(rewards) - 1
    got = rp.pellets_ahead(rewards, n)
    want = [sum(rp.AHEAD_GAMMA ** k * max(rewards[t + 1 + k], 0.0)
                for k in range(rp.AHEAD) if t + 1 + k < len(rewards)) for t in range(n)]
    np.testing.assert_allclose(got, want, rtol=1e-6)
    # the costs of accelerating are left out, and nothing comes after the episode's end
    assert got[-1] == max(rewards[-1], 0.0)


def test_ridge_r2_is_one_for_a_linear_target_and_near_zero_for_noise():
    rng = np.random.default_rng(1)
    x_tr, x_te = rng.normal(size=(400, 5)), rng.normal(size=(200, 5))
    w = np.array([1.0, -2.0, 0.5, 0.0, 3.0])
    assert rp.ridge_r2(x_tr, x_tr @ w, x_te, x_te @ w) > 0.99
    assert abs(rp.ridge_r2(x_tr, rng.normal(size=400), x_te, rng.normal(size=200))) < 0.1
