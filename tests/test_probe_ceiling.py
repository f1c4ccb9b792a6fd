"""The probe's ceiling (`cdrl.evaluation.probe_ceiling`): its starts and real returns against the
probe's, its values against a plain loop over the game, and its figures on a game whose answer
is known."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import games
from cdrl.evaluation import imagination_probe as ip
from cdrl.evaluation import probe_ceiling as pc
from cdrl.models import make_variant
from cdrl.models.arch import TINY
from envs.policies import Policy, get_policy, uniform_init


def _always(buttons):
    return Policy(f"always{buttons}", uniform_init, lambda key, ps, obs: (jnp.asarray(buttons, jnp.float32), ps))


def test_the_starts_and_real_returns_are_the_probes():
    g, env_params = games.test_game()
    variant = make_variant("final_proposal", TINY)
    params = variant.init(jax.random.PRNGKey(0))
    probe = ip.followed_branches(variant, params, g, env_params, None, games=2, points=2, every=8, horizon=3,
                                 source="variant")
    ours = pc.branches(g, env_params, get_policy("behaviour"), 0.9, games=2, points=2, every=8, horizon=3,
                       horizons=(1, 3), samples=2, steps=3)
    np.testing.assert_array_equal(ours["alive"], probe["alive"])
    np.testing.assert_array_equal(ours["real"], probe["real"])
    assert ours["value"].shape == (2, 2, 2, len(ip.SEQUENCES))


def test_the_value_is_the_mean_discounted_return_of_a_plain_loop():
    """Game 0's first start (after 8 followed steps), every sequence held H = 2 steps, then the
    behaviour policy for 3 steps, 2 samples, each step written out with the documented keys."""
    from envs.policies import privileged_policy, random_turns_instead

    g, env_params = games.test_game()
    gamma, steps, samples, every, h = 0.8, 3, 2, 8, 2
    ours = pc.branches(g, env_params, get_policy("behaviour"), gamma, games=1, points=1, every=every, horizon=3,
                       horizons=(h,), samples=samples, steps=steps)
    behaviour = get_policy("behaviour")
    step = jax.jit(g.step_state)  # one game step at a time, as a plain loop plays it
    privileged, act = jax.jit(privileged_policy(g).step), jax.jit(behaviour.step)
    k_reset, key = jax.random.split(jax.random.PRNGKey(ip.GAME_SEED))
    state = g.reset_state(k_reset, env_params)
    for _ in range(every):
        key, k_policy, k_explore, k_env = jax.random.split(key, 4)
        label, _ = privileged(k_policy, None, None, state, env_params)
        state = step(k_env, state, random_turns_instead(k_explore, label, ip.EXPLORE), env_params)[0]
    held_keys = jax.random.split(jax.random.fold_in(key, 1), 3)
    sample_keys = jax.random.split(jax.random.fold_in(key, 2), samples)
    for s, buttons in enumerate(ip.SEQUENCES.values()):
        branch = state
        for t in range(h):
            branch = step(held_keys[t], branch, jnp.asarray(buttons), env_params)[0]
        returns = []
        for k in sample_keys:
            k_init, k_run = jax.random.split(k)
            ps, cont, total = behaviour.init(k_init), branch, 0.0
            for j, kj in enumerate(jax.random.split(k_run, steps)):
                k_act, k_env = jax.random.split(kj)
                a, ps = act(k_act, ps, None)
                cont, reward, term, trunc, _ = step(k_env, cont, a, env_params)
                total += gamma ** j * float(reward)
                assert not (term or trunc)
            returns.append(total)
        assert ours["value"][0, 0, 0, s] == pytest.approx(np.mean(returns), abs=1e-5)


@pytest.mark.parametrize("buttons, value", [((0.0, 1.0, 0.0), 1.0), ((0.0, 0.0, 0.0), 0.0)])
def test_on_a_game_whose_answer_is_known(buttons, value):
    """On `games.TurnOneSlither`, turn1 held is the real best from every state. The real rewards alone
    rank it first at every start. A policy that always holds turn1 is worth sum_j γ^j after any
    sequence, one that goes straight on 0: neither changes the ranking."""
    _, env_params = games.test_game()
    game = games.TurnOneSlither(**games.SIZES)
    gamma, steps = 0.9, 4
    got = pc.ceiling(game, env_params, _always(buttons), gamma, max_steps=games.MAX_STEPS, games=2, every=8,
                     horizons=(1, 3), samples=2, steps=steps)
    assert got["starts"] == 2 * (games.MAX_STEPS // 8 - 1)
    worth = value * sum(gamma ** j for j in range(steps))
    for h in ("1", "3"):
        assert got["mean_value"][h] == pytest.approx([worth] * len(ip.SEQUENCES))
        for row in (got["rewards_only"][h], got["with_value"][h]):
            assert row["best_steer_agree"] == 1.0 and row["best_share_real"] == [0.0, 0.0, 1.0]
            assert row["corr_steer"] == pytest.approx(1.0)


@pytest.mark.parametrize("options, says", [({"every": 50}, "leave no start"), ({"horizons": (0, 3)}, "held steps"),
                                           ({"horizons": (16,)}, "held steps"), ({"samples": 0}, "one sample")])
def test_bad_options_are_refused_by_name(options, says):
    g, env_params = games.test_game()
    with pytest.raises(ValueError, match=says):
        pc.ceiling(g, env_params, "behaviour", 0.9, max_steps=games.MAX_STEPS, **options)


def test_the_attribution_swaps_one_half_at_a_time():
    """`model` is the probe's `by_horizon`; `game` ranks by the real rewards plus the played
    value; where the model imagines the real rewards, swapping them in changes nothing."""
    rng = np.random.default_rng(0)
    n, seqs, horizon, gamma, hs = 50, len(ip.SEQUENCES), 6, 0.8, (1, 3)
    real, imagined, values = (rng.choice([0.0, 0.5, -0.25], size=(n, seqs, horizon)) for _ in range(3))
    played = rng.normal(size=(n, len(hs), seqs))
    got = pc.attribution(imagined, values, real, played, gamma, hs)
    assert got["model"] == ip.horizon_scores(real, imagined, values, gamma, hs)
    for i, h in enumerate(hs):
        by_hand = ip.rank_scores(real.sum(-1), real[..., :h].sum(-1) + gamma ** h * played[:, i])
        assert got["game"][str(h)] == by_hand
    same = pc.attribution(real, values, real, played, gamma, hs)
    assert same["model"] == same["game_rewards"] and same["game_value"] == same["game"]
    assert same["model"] != same["game"]
