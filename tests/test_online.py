"""Online controller training: where the gradients go, scan against a loop, and a reward
that a controller can learn."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdrl.data.frames import model_obs
from cdrl.learners import game_batch as vec
from cdrl.learners.api import train_program
from cdrl.learners.thesis_ascent import AscentConfig, AscentHParams, Rollout, ThesisAscent, chunk_objective
from cdrl.models import make_variant
from cdrl.models.arch import TINY
import games

ARCH = TINY


@pytest.fixture(scope="module")
def game():
    return games.test_game()


def STEP(v, g, cfg, state, hp, env_params):
    return train_program(ThesisAscent(v, g, cfg, hp, env_params), state)


def rollout_carry(state):
    return Rollout(carry=jax.lax.stop_gradient(state.train.carry), games=state.games, action=state.action,
                   key=state.key)


def transition(v, g, p, env_params, noise_std, c, hp=None):
    learner = ThesisAscent(v, g, AscentConfig(num_envs=ENVS, unroll=T), hp or AscentHParams.create(), env_params)
    return learner.transition(p, jnp.zeros((), jnp.int32), noise_std, c)
# Every test shares one game, variant and shape, so the online step compiles once.
ENVS, T = 8, 8


def _state(game, hp=None):
    g, params = game
    v = make_variant("reward_prediction", ARCH)
    cfg = AscentConfig(num_envs=ENVS, unroll=T)
    hp = hp or AscentHParams.create(warmup_steps=0, ascent=0.5, noise_std=0.2)
    return v, cfg, hp, ThesisAscent(v, g, cfg, hp, params).init(jax.random.PRNGKey(0))


def test_game_outputs_carry_no_gradient(game):
    """Two transitions: the second executes the model's own action output from the first,
    which depends on the parameters (its gradient is not zero), yet what the game returns
    for it (the executed action, the reward, the next observation) carries no gradient.
    (From the initial carry alone the executed action is a constant, so one transition
    could not tell.)"""
    g, env_params = game
    v, cfg, hp, state = _state(game)

    @jax.jit
    def gradients(p):
        def two_steps(p):
            c = rollout_carry(state)
            c, _ = transition(v, g, p, env_params, hp.noise_std, c)
            fed_back = c.action  # ã_1, executed (with noise) by the next transition
            c, (_, stats) = transition(v, g, p, env_params, hp.noise_std, c)
            return fed_back, stats, c

        def model_action(p):
            return jnp.sum(two_steps(p)[0])

        def game_outputs(p):
            _, stats, c = two_steps(p)
            return jnp.sum(stats["reward"]) + jnp.sum(c.games.obs) + jnp.sum(stats["action"])

        return jax.grad(model_action)(p), jax.grad(game_outputs)(p)

    through_model, through_game = gradients(state.train.params)
    assert float(jnp.max(jnp.abs(through_model["act_dec"]["dense0"]["kernel"]))) > 0
    assert all(float(jnp.max(jnp.abs(x))) == 0.0 for x in jax.tree.leaves(through_game))


def test_reward_ascent_reaches_the_controller_only_with_scope_controller(game):
    """The ascent gradient (non-zero) changes the controller D_a; every other group gets exactly
    the update it gets with lambda = 0. With scope "all" (the same compiled program) the ascent
    moves the rest of the model too."""
    g, env_params = game
    v, cfg, _, state = _state(game)
    hp_on = AscentHParams.create(warmup_steps=0, ascent=0.5, noise_std=0.2)
    on, _ = STEP(v, g, cfg, state, hp_on, env_params)
    off, _ = STEP(v, g, cfg, state, hp_on.replace(ascent=jnp.zeros(())), env_params)
    for group in state.train.params:
        same = all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(on.train.params[group]),
                                                         jax.tree.leaves(off.train.params[group])))
        assert same == (group != "act_dec"), group
    hp_all = AscentHParams.create(warmup_steps=0, ascent=0.5, noise_std=0.2, scope="all")
    on, _ = STEP(v, g, cfg, state, hp_all, env_params)
    off, _ = STEP(v, g, cfg, state, hp_all.replace(ascent=jnp.zeros(())), env_params)
    assert not np.array_equal(on.train.params["reward_head"]["dense1"]["kernel"],
                              off.train.params["reward_head"]["dense1"]["kernel"])


def test_warmup_keeps_the_ascent_off(game):
    g, env_params = game
    v, cfg, _, state = _state(game)
    hp = AscentHParams.create(warmup_steps=5, ascent=0.5)
    a, m = STEP(v, g, cfg, state, hp, env_params)
    b, _ = STEP(v, g, cfg, state, hp.replace(ascent=jnp.zeros(())), env_params)
    assert float(m["ascent_on"]) == 0.0
    jax.tree.map(np.testing.assert_array_equal, a.train.params, b.train.params)


def test_online_scan_equals_a_python_loop(game):
    """The jitted online step's chunk (a scan) against a Python loop of its transition."""
    g, env_params = game
    v, cfg, hp, state = _state(game)
    hp = hp.replace(warmup_steps=jnp.asarray(1e9, jnp.float32))  # the loss is then the model loss
    new_state, metrics = STEP(v, g, cfg, state, hp, env_params)
    step = jax.jit(lambda p, c: transition(v, g, p, env_params, hp.noise_std, c))
    c = rollout_carry(state)
    outs, stats_loop = [], []
    for _ in range(cfg.unroll):
        c, (o, s) = step(state.train.params, c)
        outs.append(o)
        stats_loop.append(s)
    stack = lambda xs: jax.tree.map(lambda *a: jnp.stack(a), *xs)  # noqa: E731
    loss_loop, pred_loop, _ = chunk_objective(v, stack(outs), stack(stats_loop), hp)
    np.testing.assert_allclose(metrics["loss"], loss_loop, rtol=1e-5)
    np.testing.assert_allclose(metrics["terms"]["pred_reward"], pred_loop, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(new_state.games.obs, c.games.obs, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(metrics["reward"], jnp.mean(stack(stats_loop)["reward"]), rtol=1e-6)
    # The copy-last baseline and the floor on the chunk's own frames (o_t -> o_{t+1}).
    prev = np.clip(np.asarray(stack(outs)["obs"], np.float64), 0.01, 0.99)
    nxt = np.asarray(stack(outs)["target"], np.float64)
    copy = np.mean(-(nxt * np.log(prev) + (1 - nxt) * np.log(1 - prev)))
    p = np.clip(nxt, 1e-7, 1 - 1e-7)
    np.testing.assert_allclose(metrics["terms"]["copy_bce"], copy, rtol=1e-4)
    np.testing.assert_allclose(metrics["terms"]["target_entropy"], np.mean(-(p * np.log(p) + (1 - p) * np.log(1 - p))),
                               rtol=1e-4)
    # ...and the target of a step is the frame the next step sees, unless an episode ended there.
    np.testing.assert_allclose(nxt[:-1][~np.asarray(stack(stats_loop)["done"])[:-1]],
                               np.asarray(stack(outs)["obs"])[1:][~np.asarray(stack(stats_loop)["done"])[:-1]],
                               atol=1e-6)


def test_offline_variants_are_refused_online(game):
    g, env_params = game
    v = make_variant("main", ARCH)
    with pytest.raises(ValueError, match="has no controller"):
        ThesisAscent(v, g, AscentConfig(num_envs=1, unroll=2), AscentHParams.create(), env_params).init(
            jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="unknown ascent scope 'model'"):
        AscentHParams.create(scope="model")


def test_controller_learns_a_trivially_learnable_reward(game):
    """With a bonus for turning left, reward ascent teaches the controller to turn left: its
    noise-free return on held-out seeds clearly beats the uniform-random policy's."""
    from cdrl.evaluation import play
    from envs.policies import get_policy

    _, env_params = game
    g, _ = games.left_bonus_game()
    v = make_variant("reward_prediction", ARCH)
    cfg = AscentConfig(num_envs=ENVS, unroll=T)
    hp = AscentHParams.create(lr=0.1, ascent=1.0, reward_weight=0.1, warmup_steps=20, noise_std=0.3, noise_decay=0.98)
    state = ThesisAscent(v, g, cfg, hp, env_params).init(jax.random.PRNGKey(0))
    for _ in range(80):
        state, metrics = STEP(v, g, cfg, state, hp, env_params)
    assert float(metrics["ascent_on"]) == 1.0
    seeds = np.arange(1000, 1016)
    init, step, p = play.controller_policy(v, state.train.params)
    learned = play.summarize(*play.play(g, env_params, init, step, seeds, 40, params=p))
    uniform = get_policy("uniform")
    random = play.summarize(*play.play(g, env_params, uniform.init, uniform.step, seeds, 40))
    assert learned["ci95"][0] > random["ci95"][1] + 5.0, (learned, random)


def _same(a, b):
    """Equal arrays: floats to float rounding (two compiled programs may round apart), the rest
    exactly."""
    a, b = np.asarray(a), np.asarray(b)
    if np.issubdtype(a.dtype, np.floating):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5)
    else:
        np.testing.assert_array_equal(a, b)


def test_a_game_that_ends_is_replaced_by_a_new_one_and_the_others_go_on(game):
    """`step_games`: where a game ends, the new game of `reset_games` on the step's second key
    takes its place (its state and first frame); the others are the game's own step. Pinned
    against the game's functions called directly, on a step where one game of three ends and
    on one where none does (the new games are then drawn not at all)."""
    g, params = game
    games3 = vec.reset_games(g, params, jax.random.PRNGKey(1), 3, ARCH)
    # game 0 one step from its step limit: it ends on this step, games 1 and 2 go on
    games3 = games3.replace(env_state=games3.env_state.replace(
        time=games3.env_state.time.at[0].set(params.max_steps - 1)))
    action = jnp.asarray([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    step = jax.jit(lambda gs, k: vec.step_games(g, params, gs, action, k, ARCH))
    game_step = jax.jit(lambda k, states: jax.vmap(g.step, in_axes=(0, 0, 0, None))(
        jax.random.split(k, 3), states, action, params))
    new_games = jax.jit(lambda k: vec.reset_games(g, params, k, 3, ARCH))
    key, ends = jax.random.PRNGKey(2), [True, False, False]
    after, nxt, reward, stats = step(games3, key)
    k_env, k_reset = jax.random.split(key)
    obs, state, r, term, trunc, _ = game_step(k_env, games3.env_state)
    fresh = new_games(k_reset)
    _same(np.asarray(term | trunc), ends)
    _same(np.asarray(after.is_first), ends)
    _same(np.asarray(nxt), np.asarray(model_obs(obs, ARCH)))
    _same(np.asarray(reward), np.asarray(r))
    for i, end in enumerate(ends):
        expected_state = jax.tree.map(lambda x: x[i], fresh.env_state if end else state)
        expected_obs = (fresh.obs if end else model_obs(obs, ARCH))[i]
        for a, b in zip(jax.tree.leaves(jax.tree.map(lambda x: x[i], after.env_state)),
                        jax.tree.leaves(expected_state), strict=True):
            _same(np.asarray(a), np.asarray(b))
        _same(np.asarray(after.obs[i]), np.asarray(expected_obs))
    assert float(after.episode_return[0]) == 0.0 and int(after.episode_length[0]) == 0
    assert float(stats["finished_return"][0]) == pytest.approx(float(r[0]))
    games3 = after
    # the next step: no game ends, each goes on from where it is
    key = jax.random.PRNGKey(3)
    after, nxt, _, _ = step(games3, key)
    obs, state, _, term, trunc, _ = game_step(jax.random.split(key)[0], games3.env_state)
    assert not bool(jnp.any(term | trunc)) and not bool(jnp.any(after.is_first))
    for a, b in zip(jax.tree.leaves(after.env_state), jax.tree.leaves(state), strict=True):
        _same(np.asarray(a), np.asarray(b))
    _same(np.asarray(after.obs), np.asarray(model_obs(obs, ARCH)))
    _same(np.asarray(after.episode_length), np.asarray(games3.episode_length) + 1)


def test_the_update_is_sgd_on_the_model_gradient_minus_the_scoped_ascent(game):
    """The step's first update from zero momentum, -lr * (g_model - lambda * g_reward) with the
    ascent's share of every group but D_a scaled by ascent_all, against the two gradients taken
    apart by `jax.grad` of the chunk's model loss and of its mean predicted reward."""
    g, env_params = game
    v, cfg, _, state = _state(game)
    params = state.train.params

    def term(p, hp, i):
        return ThesisAscent(v, g, cfg, hp, env_params).collect(p, state)[0][i]

    for scope in ("controller", "all"):
        hp = AscentHParams.create(warmup_steps=0, ascent=0.5, noise_std=0.2, scope=scope)
        new, _ = STEP(v, g, cfg, state, hp, env_params)
        g_model, g_reward = jax.grad(term)(params, hp, 0), jax.grad(term)(params, hp, 1)
        for group in params:
            share = 1.0 if (group in v.controller_groups or scope == "all") else 0.0
            expected = jax.tree.map(lambda p, m, r: p - 0.1 * (m - 0.5 * share * r),
                                    params[group], g_model[group], g_reward[group])
            for got, want, r in zip(jax.tree.leaves(new.train.params[group]), jax.tree.leaves(expected),
                                    jax.tree.leaves(g_reward[group])):
                np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6 * (1 + float(np.abs(r).max())))
