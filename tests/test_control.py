"""Control: the reference policies and the protocol every controller is measured with, and the
learners with a replay buffer (`cdrl.learners`): its pieces against
equations and independent paths, and a reward any controller can learn; the experiment's
results pooled across invocations."""
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import games
from cdrl.evaluation import play
from cdrl.models import make_variant
from cdrl.models.arch import TINY
from cdrl.models.base import BUTTON_COMBOS
from cdrl.learners import LEARNERS, canonical, one_step_q, onpolicy_ac
from cdrl.learners import replay_base as rb
from cdrl.learners.api import train_program
from cdrl.learners.imagination import ImaginationConfig
from cdrl.learners.onpolicy_ac import OnPolicyConfig
from cdrl.models import nets
from cdrl.training.lookahead import lambda_returns
from cdrl.training.optim import HParams, OptHParams
from envs.policies import get_policy, privileged_policy
from experiments.controller import study

SEEDS = np.arange(1000, 1016)


def test_every_policy_plays_the_same_games():
    """`compare_policies` plays a learned policy on the games it plays the references on: a
    "learned" policy that is a copy of a reference gets exactly the reference's row."""
    g, params = games.test_game()
    never = get_policy("never_accelerate")
    rows = play.compare_policies(g, params, {"copy": (never.init, never.step)}, 16, games.MAX_STEPS, seed=1000)
    assert set(rows) == {"copy", *play.REFERENCES}
    assert rows["copy"] == rows["never_accelerate"]
    other = play.compare_policies(g, params, {"copy": (never.init, never.step)}, 16, games.MAX_STEPS, seed=2000,
                                  references=False)
    assert set(other) == {"copy"} and other["copy"] != rows["copy"]  # other seeds, other games


def test_never_accelerate_and_privileged_never_press_accelerate():
    g, params = games.test_game()
    obs, state = g.reset(jax.random.PRNGKey(0), params)
    never, priv = get_policy("never_accelerate"), privileged_policy(g)
    for i in range(20):
        a, _ = never.step(jax.random.PRNGKey(i), never.init(jax.random.PRNGKey(i)), obs)
        b, _ = priv.step(jax.random.PRNGKey(i), priv.init(jax.random.PRNGKey(i)), obs, state, params)
        assert float(a[2]) == 0.0 and float(b[2]) == 0.0
        obs, state, *_ = g.step(jax.random.PRNGKey(i), state, a, params)
    assert priv.privileged and not never.privileged


def test_seldom_accelerate_presses_accelerate_at_its_rate_and_turns_at_random():
    from envs.policies import SELDOM_ACCELERATE

    seldom = get_policy("seldom_accelerate")
    a = jax.vmap(lambda k: seldom.step(k, seldom.init(k))[0])(jax.random.split(jax.random.PRNGKey(0), 4000))
    pressed = np.asarray(a) > 0.5
    np.testing.assert_allclose(pressed.mean(0), [0.5, 0.5, SELDOM_ACCELERATE], atol=0.025)
    assert set(np.unique(np.asarray(a[:, 2]))) == {0.0, 1.0}


def _one_pellet(g, params, ahead: float, right: float):
    """A game state whose only pellet lies `ahead` pixels in front of the player's head and
    `right` pixels to its right, with every opponent far away."""
    _, state = g.reset(jax.random.PRNGKey(0), params)
    hx, hy, h = float(state.x[0, 0]), float(state.y[0, 0]), float(state.heading[0])
    px = hx + ahead * np.cos(h) - right * np.sin(h)
    py = hy + ahead * np.sin(h) + right * np.cos(h)
    cs, n = g.pellet_cell_size, g.grid
    ix, iy = int(px % g.arena_size // cs), int(py % g.arena_size // cs)
    value = np.zeros((n, n), np.float32)
    value[iy, ix] = 0.5
    dx = np.zeros((n, n), np.float32)
    dy = np.zeros((n, n), np.float32)
    dx[iy, ix], dy[iy, ix] = px % g.arena_size - ix * cs, py % g.arena_size - iy * cs
    far = state.x.at[1:].set(hx + g.arena_size / 2), state.y.at[1:].set(hy + g.arena_size / 2)
    return state.replace(pellet_value=jnp.asarray(value), pellet_dx=jnp.asarray(dx), pellet_dy=jnp.asarray(dy),
                         x=far[0], y=far[1])


@pytest.mark.parametrize("right, pressed", [(60.0, 0), (-60.0, 1), (0.0, None)])
def test_the_privileged_policy_turns_to_the_pellet(right, pressed):
    """A pellet 100 px ahead and 60 px to one side: the policy turns to that side (right is
    button 0, left button 1); straight ahead it presses neither. Headings grow clockwise on
    screen, y downwards: "right" of a heading h is the direction h + pi / 2."""
    g, params = games.test_game()
    state = _one_pellet(g, params, 100.0, right)
    action, _ = privileged_policy(g).step(None, None, None, state, params)
    expected = np.zeros(3)
    if pressed is not None:
        expected[pressed] = 1.0
    np.testing.assert_array_equal(np.asarray(action), expected)


def test_the_privileged_policy_outscores_random_turning():
    g, params = games.test_game()
    priv, never = privileged_policy(g), get_policy("never_accelerate")
    p = play.summarize(*play.play(g, params, priv.init, priv.step, SEEDS, games.MAX_STEPS, privileged=True))
    n = play.summarize(*play.play(g, params, never.init, never.step, SEEDS, games.MAX_STEPS))
    assert p["ci95"][0] > n["ci95"][1], (p, n)


def test_lambda_returns_against_the_recursion_with_episode_ends():
    """R_k = r_k + gamma d_k ((1 - lambda) V_{k+1} + lambda R_{k+1}), R_K = last, by a loop;
    d_k = 1 by default, and d_k = 0 ends the sum (lambda 1: the discounted rewards to the
    episode's end; lambda 0: one-step TD)."""
    rng = np.random.default_rng(0)
    r, v = rng.normal(size=(7, 2)).astype(np.float32), rng.normal(size=(7, 2)).astype(np.float32)
    last = rng.normal(size=2).astype(np.float32)
    ended = np.ones((7, 2), np.float32)
    ended[3, 0] = 0.0
    for d in (None, ended):
        for lam in (0.0, 0.6, 1.0):
            out = np.asarray(lambda_returns(*map(jnp.asarray, (r, v, last)), 0.9, lam,
                                                  None if d is None else jnp.asarray(d)))
            ref, nxt = np.zeros_like(r), last
            for k in reversed(range(7)):
                nxt = r[k] + 0.9 * (1.0 if d is None else d[k]) * ((1 - lam) * v[k] + lam * nxt)
                ref[k] = nxt
            np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-6)
    mc = np.asarray(lambda_returns(*map(jnp.asarray, (r, v, last)), 0.9, 1.0, jnp.asarray(ended)))
    assert mc[0, 0] == pytest.approx(sum(0.9 ** k * r[k, 0] for k in range(4)), rel=1e-5)


def test_real_returns_score_each_decision_by_the_rewards_after_its_buttons():
    """`real`: the output of step t chooses a_{t+1}, which earns r_{t+2} (`reward[t + 1]`); by a
    loop over the chunk, R_t = r_{t+2} + gamma ((1 - lambda) V_{t+1} + lambda R_{t+1}), cut where
    o_{t+2} starts a new episode, R_{T-1} = V_{T-1}; a decision counts unless o_{t+1} starts one."""
    rng = np.random.default_rng(1)
    t, b, gamma, lam = 6, 2, 0.9, 0.7
    reward, values = rng.normal(size=(t, b)).astype(np.float32), rng.normal(size=(t, b)).astype(np.float32)
    first = np.zeros((t, b), bool)
    first[3, 0] = True  # game 0 starts again at o_3
    after = np.array([False, True])  # game 1 starts again at o_6, after the chunk
    rets, valid = onpolicy_ac.onpolicy_returns(jnp.asarray(values), jnp.asarray(reward), jnp.asarray(first),
                                        jnp.asarray(after), gamma, lam)
    starts = np.concatenate([first, after[None]])
    ref = np.zeros((t - 1, b), np.float32)
    for j in range(b):
        nxt = values[-1, j]
        for k in reversed(range(t - 1)):
            cont = 0.0 if starts[k + 2, j] else 1.0
            nxt = reward[k + 1, j] + gamma * cont * ((1 - lam) * values[k + 1, j] + lam * nxt)
            ref[k, j] = nxt
    np.testing.assert_allclose(np.asarray(rets), ref, rtol=1e-5, atol=1e-6)
    assert ref[1, 0] == pytest.approx(reward[2, 0])  # a_2 ends game 0's episode with r_3: nothing after
    assert ref[4, 1] == pytest.approx(reward[5, 1])
    np.testing.assert_array_equal(np.asarray(valid), ~starts[1:-1])
    assert not valid[2, 0] and valid[3, 0]  # a_3 is released at a new episode's start; a_4 is drawn


def test_the_value_controller_ascends_the_exact_expected_value_of_its_buttons():
    """`value`: the 8 button combinations' probabilities under independent Bernoullis sum to 1;
    the objective's expected Q equals the sum, combination by combination, of P(combo) times
    the critic on the model's state one imagined step after pressing it (`imagine_step` by
    hand); its gradient reaches the controller's probabilities, not the Q values."""
    probs = jnp.asarray([[0.9, 0.2, 0.5], [0.1, 0.7, 0.05]])
    logp = one_step_q.button_log_probs(probs)
    np.testing.assert_allclose(np.exp(logp).sum(axis=0), 1.0, rtol=1e-5)
    combo = list(map(tuple, np.asarray(BUTTON_COMBOS))).index((1.0, 0.0, 1.0))
    np.testing.assert_allclose(np.exp(logp[combo]), [0.9 * 0.8 * 0.5, 0.1 * 0.3 * 0.05], rtol=1e-5)

    v = make_variant("final_proposal", TINY)
    params = v.init(jax.random.PRNGKey(0))
    critic = nets.init_mlp(jax.random.PRNGKey(1), (TINY.lstm_size, 8, 1), final_selu=False)
    t, b = 4, 2
    rng = np.random.default_rng(2)
    from cdrl.data.stream import Chunk
    chunk = Chunk(obs=jnp.asarray(rng.uniform(size=(t, b, 16, 16)), jnp.float32),
                  next_obs=jnp.asarray(rng.uniform(size=(t, b, 16, 16)), jnp.float32),
                  action=jnp.asarray(rng.integers(0, 2, size=(t, b, 3)), jnp.float32),
                  reward=jnp.asarray(rng.normal(size=(t, b)), jnp.float32), is_first=jnp.zeros((t, b), bool))
    carry, _, frame = rb.starts(v, params, chunk, v.init_carry(b))
    hp = rb.ReplayHParams.create(HParams.create(v), entropy=0.0)
    n = t * b
    probs = jnp.asarray(rng.uniform(0.05, 0.95, size=(n, 3)), jnp.float32)
    actor, (_, terms) = one_step_q.value_objective(v, hp, params, critic, chunk, (carry, probs, frame))
    expected = np.zeros(n)
    for a in np.asarray(BUTTON_COMBOS):
        after, _ = v.imagine_step(params, carry, None, jnp.broadcast_to(jnp.asarray(a), (n, 3)))
        q = np.asarray(rb.critic_value(critic, after["lstm"].h))
        p = np.prod(np.where(a > 0, np.asarray(probs), 1 - np.asarray(probs)), axis=-1)
        expected += p * q
    assert float(terms["imagined_return"]) == pytest.approx(expected.mean(), rel=1e-4, abs=1e-6)
    grad = jax.grad(lambda pr: one_step_q.value_objective(v, hp, params, critic, chunk, (carry, pr, frame))[0])(probs)
    assert np.abs(np.asarray(grad)).max() > 0


def test_closed_loop_minus_imagines_on_a_zero_error():
    """FinalProposal's imagination fast path (no decoder, no encoder pass per step) equals its
    ordinary step fed its own prediction, õ_t as o_t, so that o_t - õ_t = 0."""
    v = make_variant("final_proposal", TINY)
    params = v.init(jax.random.PRNGKey(0))
    carry = v.init_carry(3)
    x = jnp.asarray(np.random.default_rng(1).uniform(size=(3, 16, 16)), jnp.float32)
    a0 = jnp.full((3, 3), 0.5)
    from cdrl.models.base import StepInput
    carry, _ = v.step(params, carry, StepInput(obs=x, action=a0, is_first=jnp.ones(3, bool)))
    action = jnp.asarray([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.3, 0.3, 0.9]])
    fast_carry, fast = v.imagine_step(params, carry, None, action)
    slow_carry, slow = v.step(params, carry, StepInput(obs=carry["pred_obs"], action=action,
                                                       is_first=jnp.zeros(3, bool)))
    for k in ("action", "reward", "pred_code"):
        np.testing.assert_allclose(fast[k], slow[k], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(fast_carry["lstm"].h, slow_carry["lstm"].h, rtol=1e-5, atol=1e-6)
    assert "logits" not in fast


def test_the_replay_buffer_is_a_ring():
    v = make_variant("final_proposal", TINY)
    g, params = games.test_game()
    cfg = ImaginationConfig(num_envs=2, unroll=3, replay=2, model_updates=1, horizon=2)
    hp = rb.ReplayHParams.create(HParams.create(v))
    replay = LEARNERS["imagined_ascent"](v, g, cfg, hp, params).init(jax.random.PRNGKey(0)).replay
    carry = v.init_carry(2)
    for i in range(3):
        chunk = {"obs": jnp.full((3, 2, 16, 16), i / 10), "next_obs": jnp.full((3, 2, 16, 16), i / 10 + 0.05),
                 "action": jnp.full((3, 2, 3), float(i)), "reward": jnp.full((3, 2), float(i)),
                 "is_first": jnp.zeros((3, 2), bool)}
        replay = rb.store(replay, chunk, carry)
    assert int(replay.filled) == 2 and int(replay.cursor) == 1
    np.testing.assert_array_equal(replay.reward[:, 0, 0], [2.0, 1.0])  # chunk 2 overwrote chunk 0
    # frames stored as uint8: o_0 .. o_{T-1} then the last o_T
    assert replay.obs.dtype == jnp.uint8
    np.testing.assert_array_equal(replay.obs[0, :, 0, 0, 0], [51, 51, 51, 64])


def test_the_balanced_reward_error_weighs_each_sign_class_alike():
    """`balanced_squared_error` against the per-class means computed apart: each sign class of
    the target present weighs alike, an absent one not at all, and so one rare reward among many
    steps gets half the gradient (two classes) where the plain mean gives it 1 / steps."""
    from cdrl.models.controller import balanced_squared_error

    rng = np.random.default_rng(0)
    target = np.zeros((16, 4), np.float32)
    target[3, 1], target[9, 2], target[5, 0] = 0.5, 0.5, -0.25
    pred = rng.normal(0.0, 0.3, target.shape).astype(np.float32)
    err = (pred - target) ** 2
    expected = np.mean([err[target < 0].mean(), err[target == 0].mean(), err[target > 0].mean()])
    assert float(balanced_squared_error(jnp.asarray(pred), jnp.asarray(target))) == pytest.approx(expected, rel=1e-5)
    one = np.zeros((100,), np.float32)
    one[42] = 0.5
    pred = rng.normal(0.0, 0.3, one.shape).astype(np.float32)
    expected = np.mean([((pred - one)[one == 0] ** 2).mean(), (pred[42] - 0.5) ** 2])  # no negative class
    assert float(balanced_squared_error(jnp.asarray(pred), jnp.asarray(one))) == pytest.approx(expected, rel=1e-5)
    grad = jax.grad(lambda p: balanced_squared_error(p, jnp.asarray(one)))(jnp.asarray(pred))
    plain = jax.grad(lambda p: jnp.mean(jnp.square(p - jnp.asarray(one))))(jnp.asarray(pred))
    assert float(grad[42]) == pytest.approx(2.0 * (pred[42] - 0.5) / 2.0, rel=1e-5)
    assert float(plain[42]) == pytest.approx(2.0 * (pred[42] - 0.5) / 100.0, rel=1e-5)
    assert float(balanced_squared_error(jnp.zeros(8), jnp.zeros(8))) == 0.0  # one class, no division by absent ones


def test_the_balanced_reward_weight_reaches_the_loss_or_is_refused_by_name():
    from cdrl.runs.config import RunConfig

    cfg = RunConfig(variant="reward_prediction", controller="none", recipe="fast", reward_balanced_weight=0.003)
    hp = cfg.hparams(make_variant(cfg.variant, cfg.arch))
    assert float(hp.loss_weights["reward_balanced"]) == pytest.approx(0.003)
    assert float(hp.loss_weights["reward_mse"]) == 0.0  # the fast recipe's offline world model
    for bad in ({"variant": "main"}, {"variant": "final_proposal", "controller": "rollout"}, {"variant": "ppo"}):
        with pytest.raises(ValueError, match="reward_balanced_weight"):
            RunConfig(reward_balanced_weight=0.1, **bad)


def _left_bonus_learner(name: str):
    """A learner with a replay buffer on the left-bonus game, and its first state."""
    g, params = games.left_bonus_game()
    v = make_variant("final_proposal", TINY)
    cls = LEARNERS[canonical(name)]
    shape = dict(num_envs=8, unroll=8, replay=16, model_updates=2)
    configs = {"one_step_q": rb.ReplayConfig(**shape), "onpolicy_ac": OnPolicyConfig(**shape)}
    cfg = configs.get(cls.name, ImaginationConfig(**shape, horizon=5))
    hp = rb.ReplayHParams.create(HParams.create(v, opt=OptHParams.create(lr=0.1, momentum=0.9)), warmup_steps=5,
                                 ctrl_opt=OptHParams.create("adam", lr=1e-3), ascent=1.0, gamma=0.95, entropy=3e-3)
    learner = cls(v, g, cfg, hp, params)
    return learner, learner.init(jax.random.PRNGKey(0))


def test_controller_updates_move_the_controller_only():
    """The controller's objective changes the controller (the FC's action-code columns and
    D_a) and nothing else; the model's updates leave the controller as it was."""
    learner, state = _left_bonus_learner("imagination_ac")
    mask = learner.model.controller_mask(state.model.params)
    key = jax.random.PRNGKey(3)
    chunk, carry = _filled(state).chunk(0)
    ctrl_only, _ = jax.jit(lambda l, s, c, cr, k: l.replayed_update(s, c, cr, k, 1.0))(learner, state, chunk, carry,
                                                                                        key)
    moved = jax.tree.map(lambda a, b: np.asarray(a != b), ctrl_only.model.params, state.model.params)
    assert any(np.any(m & (k > 0)) for m, k in zip(jax.tree.leaves(moved), jax.tree.leaves(mask)))
    assert not any(np.any(m & (k == 0)) for m, k in zip(jax.tree.leaves(moved), jax.tree.leaves(mask)))
    model_only, _ = jax.jit(lambda l, s, c, cr: l.model_update(s, c, cr))(learner, state, chunk, carry)
    for new, old, k in zip(jax.tree.leaves(model_only.model.params), jax.tree.leaves(state.model.params),
                           jax.tree.leaves(mask)):
        np.testing.assert_array_equal(np.asarray(new)[np.asarray(k) > 0], np.asarray(old)[np.asarray(k) > 0])


@pytest.mark.parametrize("scope", ["controller", "all"])
def test_the_onpolicy_controller_moves_its_scope_only_and_starts_on_policy(scope):
    """`onpolicy_ac` updates the controller and the critic from the chunk just played; with scope
    `controller` the world model is untouched, with `all` its core and encoder move too. At its
    first pass the probability ratio of every decision is 1: the states it recomputes from the
    chunk's start (scope `all`) are those the buttons were drawn in while acting."""
    learner, state = _left_bonus_learner("onpolicy_ac")
    carry0 = state.model.carry
    acted, chunk, _ = jax.jit(lambda l, s: l.collect(s, 0.3))(learner, state)
    mask = learner.model.controller_mask(acted.model.params)
    one = learner.replace(config=dataclasses.replace(learner.config, epochs=1, scope=scope))
    new, terms = jax.jit(lambda l, s, c, c0: l.played_update(s, c, c0, 0.3, 1.0))(one, acted, chunk, carry0)
    assert float(terms["clip_fraction"]) == 0.0 and np.isfinite(float(terms["critic_loss"]))
    moved = jax.tree.map(lambda a, b: np.asarray(a != b), new.model.params, acted.model.params)
    assert any(np.any(m & (k > 0)) for m, k in zip(jax.tree.leaves(moved), jax.tree.leaves(mask)))
    assert any(np.any(m & (k == 0)) for m, k in zip(jax.tree.leaves(moved), jax.tree.leaves(mask))) == (scope == "all")
    core_moved = np.any(np.asarray(new.model.params["lstm"]["w_input"] != acted.model.params["lstm"]["w_input"]))
    assert core_moved == (scope == "all")
    assert any(np.any(np.asarray(a != b)) for a, b in zip(jax.tree.leaves(new.critic), jax.tree.leaves(acted.critic)))


def _filled(state):
    """The buffer with one chunk of the first frames in it."""
    s = state.replay
    return s.replace(obs=s.obs.at[0].set(jnp.round(state.games.obs[None] * 255).astype(jnp.uint8)),
                     filled=jnp.ones((), jnp.int32))


# The learners that do not steer the real game learn it in the end-to-end tier (make test's time).
@pytest.mark.parametrize("name", [pytest.param("imagination_ac", marks=pytest.mark.e2e),
                                  pytest.param("one_step_q", marks=pytest.mark.e2e), "onpolicy_ac"])
def test_the_controller_learns_a_trivially_learnable_reward(name):
    """With a bonus for turning left, the actor-critic in imagination, the action values read
    one model step ahead and the actor-critic on the real chunks teach the controller to turn
    left: its noise-free return on held-out seeds clearly beats the uniform-random policy's."""
    learner, state = _left_bonus_learner(name)
    for _ in range(60):
        state, metrics = train_program(learner, state)
    assert float(metrics["controller_on"]) == 1.0 and not bool(metrics["diverged"])
    learned, random = games.learned_and_random(learner, state, SEEDS)
    assert learned["ci95"][0] > random["ci95"][1] + 5.0, (learned, random)


@pytest.mark.e2e
def test_the_experiment_counts_a_pretrained_world_models_data(tmp_path):
    """`critic-pre` trains its world model offline first and starts the controller run from it:
    its game frames and its learning curve count the pre-training data's frames, and the
    pre-training's own figures are reported."""
    from cdrl.runs.rundir import RunDir

    budget = study.BUDGETS["tiny"]
    results = study.run_experiment(["critic-pre"], budget, [0], tmp_path)
    seed = results["configs"]["critic-pre"]["seeds"]["0"]
    pre = RunDir(tmp_path / "critic-pre" / "pretrain0").read_config()
    online = RunDir(tmp_path / "critic-pre" / "seed0").read_config()
    assert pre.kind == "offline" and pre.steps == budget.pretrain_steps and online.init_from.endswith("pretrain0")
    train, _ = study.load_episodes(pre, tmp_path / "critic-pre" / "data-cache")
    data_frames = sum(len(train[i].frames) for i in range(len(train)))
    assert seed["pretrain"]["data_frames"] == data_frames > 0
    assert seed["frames"] == online.steps * online.batch * online.unroll + data_frames
    assert seed["curve"][0][0] == online.eval_every * online.batch * online.unroll + data_frames
    assert np.isfinite(seed["pretrain"]["excess_ratio"]) and np.isfinite(seed["excess_ratio_held_out"])


@pytest.mark.parametrize("closed, opened", [("real-pre-all-bal", "real-pre-all-open-bal"),
                                             ("real-pre-all", "real-pre-all-open"), ("critic", "critic-open")])
def test_the_closed_loop_comparisons_differ_in_the_variant_alone(closed, opened):
    """Each pair the experiment reads as "does closed loop − help?" runs the same options, its
    pre-training too, but for the variant: final_proposal (x_t = o_t − õ_t) against the open-loop
    reward_prediction."""
    budget = study.BUDGETS["full"]

    def fields(cfg):
        return None if cfg is None else {k: v for k, v in dataclasses.asdict(cfg).items() if k != "init_from"}

    for make in (lambda n: study.config_of(n, budget, 3), lambda n: study.pretrain_config(n, budget, 3)):
        a, b = fields(make(closed)), fields(make(opened))
        assert (a is None) == (b is None), (closed, opened)
        if a is not None:
            assert (a.pop("variant"), b.pop("variant")) == ("final_proposal", "reward_prediction")
            assert a == b, {k: (a[k], b[k]) for k in a if a[k] != b[k]}


@pytest.mark.parametrize("imagined, real", [("critic-pre-bal", "real-pre-all-bal")])
def test_the_imagination_comparison_shares_its_world_models_pre_training(imagined, real):
    """The pair read as "does the actor-critic in imagination control where the one on real
    returns does?" starts from the same pre-trained world model (the same pre-training run for
    every seed) and differs online in the controller."""
    budget = study.BUDGETS["full"]
    for seed in (0, 3):
        assert study.pretrain_config(imagined, budget, seed) == study.pretrain_config(real, budget, seed)
        a, b = study.config_of(imagined, budget, seed), study.config_of(real, budget, seed)
        assert (a.variant, a.learner, b.learner) == (b.variant, "imagination_ac", "onpolicy_ac")


def test_the_clipped_planner_keeps_its_world_models_training_online():
    """`plan-pre-clip`'s world model learns online as it was pre-trained: the same look-ahead,
    clip, heads' gradient, discount and balanced reward weights, read back from both configs."""
    budget = study.BUDGETS["full"]
    pre, online = study.pretrain_config("plan-pre-clip", budget, 0), study.config_of("plan-pre-clip", budget, 0)
    fields = ("lookahead_steps", "head_grad", "grad_clip", "gamma", "reward_balanced_weight",
              "imagined_reward_balanced_weight")
    expected = [3, 1e-3, 0.05, 0.9, 0.003, 0.003]
    assert [getattr(pre, f) for f in fields] == [getattr(online, f) for f in fields] == expected
    assert (pre.learner, online.learner, online.horizon) == ("world_model", "mpc_planner", 5)


def _seed_result(ret, references, length=180.0):
    return {"return": ret, "length": length, "frames": 96, "curve": [[48, ret - 1.0], [96, ret]],
            "references": references, "excess_ratio_held_out": 0.5 + ret / 10,
            "reward_fit": {"correlation": ret / 10, "r2": ret / 20}}


def _results(per_config, references, seeds, **budget):
    return {"budget": {**dataclasses.asdict(study.BUDGETS["tiny"]), **budget, "seeds": seeds},
            "references": references,
            "configs": {name: _row(name, {str(s): _seed_result(r, references) for s, r in rows.items()})
                        for name, rows in per_config.items()}}


def _row(name, per_seed):
    return study.summarise(study.CONFIGS[name], per_seed)


REFS = {"never_accelerate": {"mean_return": 2.5, "ci95": [2.0, 3.0], "episodes": 4, "mean_length": 180.0}}


def test_merged_results_pool_the_seeds_and_recompute_the_figures_across_them():
    """Seeds run in two invocations, merged: the pooled per-seed rows, and mean, sample
    standard deviation and the Student-t 95 % CI over the three seeds, pinned against the
    formula with t(0.975, 2 dof) = 4.3027 from the table."""
    a = _results({"critic": {0: 1.0, 1: 3.0}, "ppo": {0: 5.0}}, REFS, [0, 1], name="full")
    b = _results({"critic": {2: 2.0}}, REFS, [2], name="full")
    merged = study.merge([a, b])
    row = merged["configs"]["critic"]
    assert list(row["seeds"]) == ["0", "1", "2"] and merged["budget"]["seeds"] == [0, 1, 2]
    assert row["return"]["per_seed"] == [1.0, 3.0, 2.0]
    assert row["return"]["mean"] == pytest.approx(2.0) and row["return"]["std"] == pytest.approx(1.0)
    half = 4.3027 * 1.0 / np.sqrt(3)
    assert row["return"]["ci95"] == pytest.approx([2.0 - half, 2.0 + half], abs=1e-3)
    assert row["excess_ratio_held_out"]["mean"] == pytest.approx(0.7)
    assert row["reward_fit"]["correlation"]["per_seed"] == pytest.approx([0.1, 0.3, 0.2])
    assert merged["configs"]["ppo"]["return"]["per_seed"] == [5.0]  # a configuration only one part ran
    assert merged["references"] == REFS


def test_merging_refuses_results_of_other_games_budgets_or_conflicting_seeds():
    a = _results({"critic": {0: 1.0}}, REFS, [0])
    other_games = {"never_accelerate": {**REFS["never_accelerate"], "mean_return": 2.6}}
    with pytest.raises(ValueError, match="other held-out games"):
        study.merge([a, _results({"critic": {1: 2.0}}, other_games, [1])])
    with pytest.raises(ValueError, match="differs in frames, level"):
        study.merge([a, _results({"critic": {1: 2.0}}, REFS, [1], frames=192, level="heading")])
    with pytest.raises(ValueError, match="seed 0 of configuration 'critic' differs"):
        study.merge([a, _results({"critic": {0: 1.5}}, REFS, [0])])
    with pytest.raises(ValueError, match="not a control experiment's result"):
        study.merge([a, {"configs": {}}])
    assert study.merge([a, a])["configs"]["critic"]["return"]["per_seed"] == [1.0]  # the same seed twice
    read_back = json.loads(json.dumps(_results({"critic": {1: 2.0}}, REFS, [1])))  # tuples become lists
    assert study.merge([a, read_back])["configs"]["critic"]["return"]["per_seed"] == [1.0, 2.0]


def test_the_study_merges_result_files_and_names_a_bad_one(tmp_path):
    """`python -m experiments.controller.study --merge` writes `study.merge`'s result and the
    files it came from; an unreadable file is named in the error and nothing is written."""
    script = ["-m", "experiments.controller.study"]
    root = Path(__file__).resolve().parents[1]
    a = _results({"critic": {0: 1.0, 1: 3.0}}, REFS, [0, 1], name="full")
    b = _results({"critic": {2: 2.0}}, REFS, [2], name="full")
    (tmp_path / "a.json").write_text(json.dumps(a))
    (tmp_path / "b.json").write_text(json.dumps(b))
    out = tmp_path / "merged.json"
    subprocess.run([sys.executable, *script, "--merge", str(tmp_path / "a.json"), str(tmp_path / "b.json"),
                    "--out", str(out)], check=True, capture_output=True, text=True, cwd=root)
    merged = json.loads(out.read_text())
    assert merged.pop("merged_from") == [str(tmp_path / "a.json"), str(tmp_path / "b.json")]
    assert merged == json.loads(json.dumps(study.merge([a, b])))

    (tmp_path / "broken.json").write_text("{\"budget\": ")
    bad = subprocess.run([sys.executable, *script, "--merge", str(tmp_path / "a.json"),
                          str(tmp_path / "broken.json"), "--out", str(tmp_path / "never.json")],
                         capture_output=True, text=True, cwd=root)
    assert bad.returncode != 0 and "broken.json" in bad.stderr and not (tmp_path / "never.json").exists()


def test_random_turns_instead_replaces_a_share_with_random_turns():
    from envs.policies import random_turns_instead

    buttons = jnp.array([1.0, 0.0, 1.0])
    keys = jax.random.split(jax.random.PRNGKey(0), 4000)
    out = np.asarray(jax.vmap(lambda k: random_turns_instead(k, buttons, 0.2))(keys))
    replaced = np.any(out != np.asarray(buttons), axis=1) | (out[:, 2] == 0.0)
    assert abs(replaced.mean() - 0.2) < 0.03
    assert np.all(out[replaced, 2] == 0.0)  # random turns never accelerate
    assert abs(out[replaced, :2].mean() - 0.5) < 0.06 and set(np.unique(out)) <= {0.0, 1.0}
    np.testing.assert_array_equal(jax.vmap(lambda k: random_turns_instead(k, buttons, 0.0))(keys[:50]),
                                  np.broadcast_to(buttons, (50, 3)))


def test_each_configuration_is_paired_with_ppo_seed_by_seed():
    """`paired_vs_ppo` is the mean and Student-t CI of the per-seed differences against PPO on
    the same seeds (t(0.975, 2 dof) = 4.3027 from the table); PPO itself has none."""
    results = _results({"critic": {0: 1.0, 1: 3.0, 2: 2.0}, "ppo": {0: 5.0, 1: 2.0, 2: 2.0}}, REFS, [0, 1, 2])
    study.pair_with(results, "ppo")
    paired = results["configs"]["critic"]["paired_vs_ppo"]
    assert paired["per_seed"] == [-4.0, 1.0, 0.0] and paired["of"] == "return"
    std = np.std([-4.0, 1.0, 0.0], ddof=1)
    assert paired["mean"] == pytest.approx(-1.0) and paired["std"] == pytest.approx(std)
    assert paired["ci95"] == pytest.approx([-1.0 - 4.3027 * std / np.sqrt(3), -1.0 + 4.3027 * std / np.sqrt(3)],
                                           abs=1e-3)
    assert "paired_vs_ppo" not in results["configs"]["ppo"]


def test_a_budget_that_counts_every_frame_gives_the_online_part_what_the_data_left():
    """At the 48k budget a pre-trained configuration's online run gets 48 000 game frames less
    its pre-training data's; PPO gets all of them; data that leaves less than a chunk is refused."""
    budget = study.BUDGETS["48k"]
    planned = study.config_of("plan-pre", budget, 0, None, data_frames=9_364)
    assert planned.steps == (48_000 - 9_364) // (planned.batch * planned.unroll)
    ppo = study.config_of("ppo", budget, 0)
    assert ppo.steps * ppo.batch * ppo.unroll == 48_000 - 48_000 % (ppo.batch * ppo.unroll)
    assert study.config_of("plan-pre", study.BUDGETS["full"], 0, None, data_frames=9_364).steps == 38_400 // 128
    with pytest.raises(ValueError, match="leave .* less than one chunk"):
        study.config_of("plan-pre", budget, 0, None, data_frames=47_990)
