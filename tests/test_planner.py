"""The learners that look ahead through the model: the planner's scores and the imagined
actor-critic's returns against plain written-out loops; on the left-bonus game, the planner and
the ascent with the value at the end each beat the uniform-random policy; the policy video's
recorder against `play`."""
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import games
from cdrl.evaluation import play
from cdrl.learners import LEARNERS
from cdrl.learners import replay_base as rb
from cdrl.learners.api import train_program
from cdrl.learners.imagination import ImaginationConfig
from cdrl.learners.mpc_planner import JITTER, plan, planner_fns
from cdrl.models import TINY, StepInput, make_variant, nets
from cdrl.models.base import BUTTON_COMBOS
from cdrl.training import lookahead as la
from cdrl.training.optim import HParams, OptHParams

B, HORIZON, GAMMA = 2, 3, 0.9
SEEDS = np.arange(1000, 1016)


def _np_expected(p, h, bins):
    """A two-hot head's expected value, in NumPy: symexp of the bins' mean under its softmax."""
    z = np.asarray(jax.nn.selu(h @ p["dense0"]["kernel"] + p["dense0"]["bias"]) @ p["dense1"]["kernel"]
                   + p["dense1"]["bias"])
    e = np.exp(z - z.max(-1, keepdims=True))
    m = (e / e.sum(-1, keepdims=True)) @ np.asarray(bins)
    return np.sign(m) * np.expm1(np.abs(m))


def _by_hand(variant, look, params, carry, x):
    """[B, 8]: every button combination pressed with the frames of `x` and held HORIZON - 1
    imagined steps more, step by step in Python."""
    scores = np.zeros((x.obs.shape[0], 8))
    for c, buttons in enumerate(itertools.product((0.0, 1.0), repeat=3)):
        action = jnp.broadcast_to(jnp.asarray(buttons, jnp.float32), (x.obs.shape[0], 3))
        cr, out = variant.step(params, carry, StepInput(obs=x.obs, action=action, is_first=x.is_first))
        for k in range(HORIZON):
            if k:
                cr, out = variant.imagine_step(params, cr, fr, action)
            fr = jax.nn.sigmoid(out["logits"] if "logits" in out else variant.decode(params, out["pred_code"]))
            h = np.asarray(variant.features(cr))
            r = np.asarray(out["reward"]) if look is None else _np_expected(params["lookahead"]["reward"], h,
                                                                            look.bin_values)
            scores[:, c] += GAMMA ** k * r
            if k == 0 and look is not None and look.advantage:  # one-step plans, by the advantage alone
                p = params["lookahead"]["advantage"]
                first_a = np.asarray(jax.nn.selu(h @ p["dense0"]["kernel"] + p["dense0"]["bias"])
                                     @ p["dense1"]["kernel"] + p["dense1"]["bias"])[:, 0]
        if look is not None and look.advantage:
            scores[:, c] = first_a
            continue
        if look is not None and look.frame_value:  # the frame value of the last predicted frame
            fv = params["lookahead"]["frame_value"]
            code = np.asarray(nets.obs_encoder(fv["enc"], variant.arch, fr))
            scores[:, c] += GAMMA ** HORIZON * _np_expected(fv["mlp"], code, look.bin_values)
        elif look is not None:  # the value head's return counts the last step's reward again: take it out
            v = _np_expected(params["lookahead"]["value"], h, look.bin_values)
            scores[:, c] += GAMMA ** HORIZON * (v - r) / float(look.gamma)
    return scores


@pytest.mark.parametrize("name, heads", [("final_proposal", "value"), ("final_proposal", None),
                                         ("reward_prediction", "value"), ("final_proposal", "frame_value"),
                                         ("reward_prediction", "advantage")])
def test_the_plans_scores_are_the_held_buttons_predicted_returns_plus_the_value(name, heads):
    """A plan's score: its buttons pressed with the real frame (the model's real step from the
    state before it), held through the imagined steps after; the best plan's buttons press now.
    The value at its end: the value head's after the last reward, or the frame value of the
    last predicted frame. With an advantage head the plans are one step, scored by it alone."""
    variant = make_variant(name, TINY)
    look = la.LookaheadHParams.create(steps=2, frame_value=heads == "frame_value",
                                      advantage=heads == "advantage") if heads else None
    key = jax.random.PRNGKey(0)
    params = la.with_heads(variant, variant.init(key), key, look)
    if heads:  # heads that predict something: random last layers (they start at zero)
        for i, p in enumerate((params["lookahead"]["reward"], params["lookahead"]["value"],
                               params["lookahead"].get("frame_value", {}).get("mlp"),
                               params["lookahead"].get("advantage"))):
            if p is not None:
                p["dense1"]["kernel"] = 0.3 * jax.random.normal(jax.random.PRNGKey(i + 1), p["dense1"]["kernel"].shape)
    frames = jax.random.uniform(jax.random.PRNGKey(5), (2, B, TINY.image_size, TINY.image_size))
    x = StepInput(obs=frames[0], action=jnp.asarray([[1.0, 0.0, 1.0], [0.0, 1.0, 0.0]]),
                  is_first=jnp.ones((B,), bool))
    carry, _ = variant.step(params, variant.init_carry(B), x)
    x = StepInput(obs=frames[1], action=jnp.zeros((B, 3)), is_first=jnp.asarray([False, True]))
    scores, best = plan(variant, look, params, carry, x, jnp.float32(GAMMA), HORIZON, jax.random.PRNGKey(9))
    expected = _by_hand(variant, look, params, carry, x)
    np.testing.assert_allclose(np.asarray(scores), expected, rtol=2e-4, atol=2e-5)
    assert np.ptp(expected, axis=1).min() > 1e-3  # the plans differ, so the choice below means something
    np.testing.assert_array_equal(np.asarray(best), BUTTON_COMBOS[expected.argmax(axis=1)])


def _left_bonus_learner(name: str, lookahead_steps: int, horizon: int):
    g, params = games.left_bonus_game()
    v = make_variant("final_proposal", TINY)
    look = la.LookaheadHParams.create(steps=lookahead_steps, head_opt=OptHParams.create("adam", lr=1e-3))
    cfg = ImaginationConfig(num_envs=8, unroll=8, replay=16, model_updates=2, horizon=horizon)
    hp = rb.ReplayHParams.create(HParams.create(v, opt=OptHParams.create(lr=0.1, momentum=0.9), lookahead=look),
                                 warmup_steps=5, ctrl_opt=OptHParams.create("adam", lr=1e-3), ascent=1.0, gamma=0.95,
                                 entropy=3e-3)
    learner = LEARNERS[name](v, g, cfg, hp, params)
    return learner, learner.init(jax.random.PRNGKey(0))


@pytest.mark.parametrize("name, updates", [("mpc_planner", 15), ("imagined_ascent", 20)])
def test_a_learner_that_looks_ahead_learns_the_left_bonus(name, updates):
    """With a bonus for turning left, the planner (three steps, the value at the end) and the
    ascent through imagined rollouts (five steps, the value at the end), their world models
    trained with the look-ahead, clearly beat the uniform-random policy on held-out seeds."""
    learner, state = _left_bonus_learner(name, lookahead_steps=2, horizon=3 if name == "mpc_planner" else 5)
    for _ in range(updates):
        state, metrics = train_program(learner, state)
    assert not bool(metrics["diverged"]) and np.isfinite(float(metrics["terms"]["model_value_twohot"]))
    learned, random = games.learned_and_random(learner, state, SEEDS)
    assert learned["ci95"][0] > random["ci95"][1] + 5.0, (learned, random)
    if name == "mpc_planner":  # one compiled program per variant and horizon
        assert learner.policy(state)[0] is planner_fns(learner.model, 3)[0]


def test_a_recorded_game_is_the_game_play_counts_and_shows_the_plans(tmp_path):
    """`cdrl eval --policy --video`'s recorder plays the game `play` plays for the same seed
    (same return and length), keeps the screen, the view and the planner's scores, and the
    buttons it pressed are the best plan's of the same step; the GIF has a frame a step."""
    from PIL import Image

    from cdrl.analysis.animation import write_gif
    from cdrl.analysis.policy_video import frame_images, record

    learner, state = _left_bonus_learner("mpc_planner", lookahead_steps=2, horizon=3)
    for _ in range(3):
        state, _ = train_program(learner, state)
    g, params = learner.game, learner.env_params
    policy = learner.policy(state)
    game = record(g, params, policy, 1003, games.MAX_STEPS, arch=learner.arch)
    returns, lengths = play.play(g, params, policy[0], policy[1], [1003], games.MAX_STEPS, params=policy[2])
    assert game["return"] == pytest.approx(float(returns[0]), abs=1e-5) and game["length"] == int(lengths[0])
    n = game["length"]
    assert game["screen"].shape == (n, 300, 500, 3) and game["screen"].dtype == np.uint8
    assert game["view"].shape == (n, TINY.image_size, TINY.image_size) and game["scores"].shape == (n, 8)
    top2 = np.sort(game["scores"], axis=1)[:, -2:]
    clear = np.flatnonzero(top2[:, 1] - top2[:, 0] > 2 * JITTER)  # no tie the planner's jitter breaks
    assert clear.size > n // 2
    np.testing.assert_array_equal(game["action"][clear], BUTTON_COMBOS[game["scores"][clear].argmax(axis=1)])
    path = write_gif(frame_images(game, "test"), tmp_path / "game.gif", 100)
    assert Image.open(path).n_frames == n


def test_the_imagined_actor_critic_ends_its_returns_on_the_look_ahead_value():
    """With the look-ahead heads, `imagination_ac`'s λ-returns take the reward head's rewards and
    end on the value head's value (fitted to real returns): its imagined return equals the
    λ-return written out step by step over the same imagined rollout."""
    from cdrl.learners.imagination import imagine
    from cdrl.learners.replay_base import critic_value, starts

    learner, state = _left_bonus_learner("imagination_ac", lookahead_steps=2, horizon=3)
    params = state.model.params
    for i, head in enumerate(("reward", "value")):  # heads that predict something
        p = params["lookahead"][head]["dense1"]
        p["kernel"] = 0.3 * jax.random.normal(jax.random.PRNGKey(i + 1), p["kernel"].shape)
    chunk, carry = state.replay.chunk(0)  # blank frames: the states still differ step by step
    begin = starts(learner.model, params, chunk, carry)
    key = jax.random.PRNGKey(7)
    _, (_, terms) = learner.objective(params, state.critic, *begin, key)
    traj = imagine(learner.model, 3, params, *begin, key, sample=True)
    look, hp = learner.hp.model.lookahead, learner.hp
    h = np.asarray(traj["h"])
    rewards = _np_expected(params["lookahead"]["reward"], h, look.bin_values)
    values = np.array(critic_value(state.critic, traj["h"]))
    values[-1] = (_np_expected(params["lookahead"]["value"], h[-1], look.bin_values) - rewards[-1]) / float(look.gamma)
    ret = values[-1]
    for k in reversed(range(3)):
        ret = rewards[k] + float(hp.gamma) * ((1 - float(hp.lam)) * values[k] + float(hp.lam) * ret)
    assert float(terms["imagined_return"]) == pytest.approx(float(np.mean(ret)), rel=1e-4, abs=1e-5)


def test_the_oracle_planner_presses_what_the_true_game_rewards():
    """With the true game as its model, the planner holds turn1 alone on `games.TurnOneSlither`
    (the only rewarded buttons; a tie goes to the first combination, so turn1 without
    accelerating), whatever its value's policy; on the left-bonus game it beats uniform random."""
    from cdrl.learners.mpc_planner import oracle_planner
    from envs.policies import get_policy

    _, env_params = games.test_game()
    turn_one = games.TurnOneSlither(**games.SIZES)
    oracle = oracle_planner(turn_one, get_policy("behaviour"), GAMMA, 2, samples=2, steps=3)
    _, state = turn_one.reset(jax.random.PRNGKey(0), env_params)
    act = jax.jit(oracle.step)
    for t in range(3):
        buttons, _ = act(jax.random.PRNGKey(t), None, None, state, env_params)
        np.testing.assert_array_equal(buttons, [0.0, 1.0, 0.0])
        state = turn_one.step_state(jax.random.PRNGKey(10 + t), state, jnp.asarray([1.0, 0.0, 0.0]), env_params)[0]

    g, params = games.left_bonus_game()
    oracle = oracle_planner(g, get_policy("never_accelerate"), GAMMA, 2, samples=2, steps=3)
    planned = play.summarize(*play.play(g, params, oracle.init, oracle.step, SEEDS, games.MAX_STEPS, privileged=True))
    uniform = get_policy("uniform")
    random = play.summarize(*play.play(g, params, uniform.init, uniform.step, SEEDS, games.MAX_STEPS))
    assert planned["ci95"][0] > random["ci95"][1], (planned, random)


def test_the_branch_probe_compares_the_eight_scores_of_each_state():
    """`branch_value_probe.scores`: learnt scores equal to the true ones correlate 1 within each
    state and pick its best; reversed ones correlate −1 and never pick it; states after the
    game's end are left out."""
    from experiments.controller import branch_value_probe as bvp

    rng = np.random.default_rng(0)
    true_r, true_v = rng.normal(size=(2, 5, 8)), rng.normal(size=(2, 5, 8))
    on = np.ones((2, 5), bool)
    on[1, 3:] = False
    same = bvp.scores((true_r, true_v, true_r, true_v, on))
    assert same["states"] == 8
    for part in ("score", "reward", "value", "steer_score", "steer_value"):
        assert same[part]["corr_within"] == pytest.approx(1.0) and same[part]["best_agrees"] == 1.0
        assert same[part]["corr_levels"] == pytest.approx(1.0)
    flipped = bvp.scores((-true_r, -true_v, true_r, true_v, on))
    assert flipped["score"]["corr_within"] == pytest.approx(-1.0) and flipped["score"]["best_agrees"] == 0.0
    assert flipped["value"]["spread_learnt"] == pytest.approx(flipped["value"]["spread_true"])
