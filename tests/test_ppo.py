"""The PPO baseline: GAE and the clipped loss against NumPy, the rollout against a Python loop,
the step's updates on its own rollout (on-policy at learning rate 0), and a reward PPO learns."""
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import games
from cdrl.models.arch import SMALL, THESIS, TINY
from cdrl.learners import ppo
from cdrl.learners.api import train_program
from cdrl.learners.ppo import PPO, PPOConfig, PPOHParams

ARCH = TINY
# Every test shares this shape and the one game, so each program compiles once.
CFG = PPOConfig(num_envs=8, unroll=16, epochs=4, minibatches=4)

def _learner(g, env_params, hp=None, cfg=CFG):
    return PPO(ARCH, g, cfg, PPOHParams.create() if hp is None else hp, env_params)


@jax.jit
def _collect(learner, state):
    rolled, (traj, last_value) = learner.collect(state)
    return rolled, traj, last_value


def _rollout(arch, g, cfg, state, env_params):
    return _collect(PPO(arch, g, cfg, PPOHParams.create(), env_params), state)


def _ppo_step(arch, g, cfg, state, hp, env_params):
    return train_program(PPO(arch, g, cfg, hp, env_params), state)


def _copy(tree):
    """A copy for `ppo_step`, which donates its state."""
    return jax.tree.map(jnp.copy, tree)


@pytest.fixture(scope="module")
def start():
    # The left-bonus game throughout: the learning test needs it, and one game means one compilation.
    g, env_params = games.left_bonus_game()
    hp = PPOHParams.create()
    return g, env_params, hp, _learner(g, env_params, hp).init(jax.random.PRNGKey(0))


def test_gae_matches_a_numpy_loop():
    rng = np.random.default_rng(0)
    t, b, gamma, lam = 9, 5, 0.97, 0.9
    rewards, values = rng.normal(size=(t, b)).astype(np.float32), rng.normal(size=(t, b)).astype(np.float32)
    dones, last = rng.random((t, b)) < 0.25, rng.normal(size=b).astype(np.float32)
    adv = ppo.gae(jnp.asarray(rewards), jnp.asarray(values), jnp.asarray(dones), jnp.asarray(last),
                  jnp.float32(gamma), jnp.float32(lam))
    ref = np.zeros((t, b))
    for j in range(b):
        a_next, v_next = 0.0, float(last[j])
        for i in reversed(range(t)):
            nd = 0.0 if dones[i, j] else 1.0
            delta = rewards[i, j] + gamma * v_next * nd - values[i, j]
            a_next = delta + gamma * lam * nd * a_next
            ref[i, j], v_next = a_next, values[i, j]
    np.testing.assert_allclose(adv, ref, atol=1e-5)
    # A done at the last step ignores the bootstrap value.
    np.testing.assert_allclose(ppo.gae(jnp.ones((1, 1)), jnp.zeros((1, 1)), jnp.ones((1, 1), bool),
                                       jnp.full((1,), 100.0), gamma, lam), [[1.0]])


def test_clipped_loss_matches_numpy():
    """Ratios inside and outside [1 - eps, 1 + eps], advantages of both signs, value updates
    inside and outside the value clip; the loss, its terms and the surrogate's gradient (zero
    exactly where the clip binds)."""
    hp = PPOHParams.create(clip_eps=0.2, value_coef=0.7, entropy_coef=0.03)
    log_ratio = np.array([-0.5, -0.1, 0.0, 0.1, 0.3, 0.5, -0.3, 0.15])
    adv = np.array([1.0, -2.0, 0.5, 1.5, 2.0, -1.0, -0.5, 3.0])
    old_lp = np.linspace(-3.0, -1.0, 8)
    new_lp = old_lp + log_ratio
    old_v = np.array([0.0, 1.0, -1.0, 2.0, 0.5, 0.0, 1.0, -0.5])
    new_v = old_v + np.array([0.5, -0.1, 0.3, 0.05, -0.4, 0.1, 0.0, 0.25])
    ret = np.array([1.0, 0.0, 0.5, 2.0, -1.0, 3.0, 1.0, 0.0])
    ent = np.array([2.0, 1.5, 1.0, 0.5, 2.0, 1.8, 1.2, 0.9])
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731

    def surrogate(nlp):
        return ppo.clipped_loss(nlp, f32(old_lp), f32(adv), f32(new_v), f32(old_v), f32(ret), f32(ent), hp)

    (loss, terms), grad = jax.value_and_grad(surrogate, has_aux=True)(f32(new_lp))

    eps = 0.2
    a = (adv - adv.mean()) / (adv.std() + 1e-8)
    r = np.exp(log_ratio)
    pg = -np.mean(np.minimum(r * a, np.clip(r, 1 - eps, 1 + eps) * a))
    vc = old_v + np.clip(new_v - old_v, -eps, eps)
    vl = 0.5 * np.mean(np.maximum((new_v - ret) ** 2, (vc - ret) ** 2))
    np.testing.assert_allclose(terms["policy_loss"], pg, rtol=1e-5)
    np.testing.assert_allclose(terms["value_loss"], vl, rtol=1e-5)
    np.testing.assert_allclose(terms["entropy"], ent.mean(), rtol=1e-6)
    np.testing.assert_allclose(loss, pg + 0.7 * vl - 0.03 * ent.mean(), rtol=1e-5)
    np.testing.assert_allclose(terms["approx_kl"], np.mean(r - 1 - log_ratio), rtol=1e-4)
    outside = np.abs(r - 1) > eps
    assert outside.sum() == 4  # ratios 0.61, 0.74, 1.35 and 1.65
    np.testing.assert_allclose(terms["clip_frac"], outside.mean())
    binds = ((r > 1 + eps) & (a > 0)) | ((r < 1 - eps) & (a < 0))
    ref_grad = np.where(binds, 0.0, -r * a / len(r))  # d(-mean(r a)) / d log_prob
    np.testing.assert_allclose(grad, ref_grad, rtol=1e-5, atol=1e-7)
    assert binds.sum() >= 1 and (outside & ~binds).sum() >= 1  # both sides of the clip are exercised


def test_log_prob_and_entropy_of_the_three_buttons():
    """Over the 8 button combinations the probabilities sum to 1 and their entropy is the sum
    of the buttons' entropies."""
    logits = jnp.asarray([[0.3, -1.2, 2.5], [0.0, 0.0, 0.0], [-4.0, 3.0, 0.7]], jnp.float32)
    combos = jnp.asarray(list(itertools.product([0.0, 1.0], repeat=3)), jnp.float32)  # [8, 3]
    lp = jax.vmap(lambda a: ppo.log_prob(logits, a))(combos)  # [8, 3 rows]
    p = np.exp(np.asarray(lp, np.float64))
    np.testing.assert_allclose(p.sum(axis=0), 1.0, rtol=1e-5)
    np.testing.assert_allclose(ppo.entropy(logits), -(p * np.log(p)).sum(axis=0), rtol=1e-5)
    np.testing.assert_allclose(ppo.entropy(jnp.zeros((3,))), 3 * np.log(2), rtol=1e-6)
    # A pressed button has probability sigmoid(logit).
    sig = 1 / (1 + np.exp(-np.asarray(logits, np.float64)))
    np.testing.assert_allclose(p[-1], sig.prod(axis=1), rtol=1e-5)


def test_network_shapes_and_initial_policy(start):
    state = start[-1]
    params = state.params
    assert set(params) == {"obs_enc", "torso", "policy", "value"}
    assert params["policy"]["kernel"].shape == (CFG.hidden, 3) and params["value"]["kernel"].shape == (CFG.hidden, 1)
    glorot_std = np.sqrt(2.0 / (CFG.hidden + 3))  # of the project's Glorot-uniform init
    assert 0.005 < np.std(params["policy"]["kernel"]) / glorot_std < 0.02
    assert 0.5 < np.std(params["value"]["kernel"]) / np.sqrt(2.0 / (CFG.hidden + 1)) < 2.0
    logits, value = ppo.policy_value(ARCH, params, state.games.obs)
    assert logits.shape == (CFG.num_envs, 3) and value.shape == (CFG.num_envs,)
    assert float(jnp.max(jnp.abs(logits))) < 0.1  # near-uniform buttons at the start
    for arch in (SMALL, THESIS):
        p = jax.eval_shape(lambda k, a=arch: ppo.init_params(a, k, 32), jax.random.PRNGKey(0))
        out = jax.eval_shape(lambda p, o, a=arch: ppo.policy_value(a, p, o), p,
                             jax.ShapeDtypeStruct((2, 5, arch.image_size, arch.image_size), jnp.float32))
        assert out[0].shape == (2, 5, 3) and out[1].shape == (2, 5)


def test_rollout_equals_a_python_loop(start):
    """Three rollouts (48 steps: every game reaches the 40-step cap and is reset) against a loop
    of the jitted transition; the episode bookkeeping against the recorded rewards and dones;
    the recorded log-probs recomputed from the recorded frames and buttons."""
    g, env_params, _, state = start
    trajs, s = [], state
    for _ in range(3):
        s, traj, last_value = _rollout(ARCH, g, CFG, s, env_params)
        trajs.append(traj)
    traj = jax.tree.map(lambda *x: np.concatenate(x), *trajs)
    step = jax.jit(lambda c: _learner(g, env_params).transition(state.params, c))
    c, records = (state.games, state.key), []
    for _ in range(3 * CFG.unroll):
        c, r = step(c)
        records.append(r)
    loop = jax.tree.map(lambda *x: np.stack(x), *records)
    for k in ("obs", "log_prob", "value", "reward"):
        np.testing.assert_allclose(traj[k], loop[k], rtol=1e-5, atol=1e-6, err_msg=k)
    for k in ("action", "done", "finished_length"):
        np.testing.assert_array_equal(traj[k], loop[k], err_msg=k)
    games, _ = c
    np.testing.assert_allclose(s.games.obs, games.obs, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(last_value, ppo.policy_value(ARCH, state.params, games.obs)[1], rtol=1e-5, atol=1e-6)
    assert set(np.unique(traj["action"])) <= {0.0, 1.0}

    # Episodes: returns and lengths counted from the records themselves.
    done, reward = traj["done"], traj["reward"]
    assert done[39].all() and done.sum() == CFG.num_envs  # the cap (no game collided in this run)
    ret, length = np.zeros(CFG.num_envs), np.zeros(CFG.num_envs, int)
    for t in range(done.shape[0]):
        ret, length = ret + reward[t], length + 1
        np.testing.assert_allclose(traj["finished_return"][t], np.where(done[t], ret, 0.0), rtol=1e-5, atol=1e-5)
        np.testing.assert_array_equal(traj["finished_length"][t], np.where(done[t], length, 0))
        ret, length = np.where(done[t], 0.0, ret), np.where(done[t], 0, length)
    np.testing.assert_allclose(s.games.episode_return, ret, rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(s.games.episode_length, length)
    np.testing.assert_array_equal(s.games.env_state.time, length)  # the reset games started afresh

    # The recorded log-probs are the network's on the recorded frames and buttons.
    logits, _ = ppo.policy_value(ARCH, state.params, jnp.asarray(traj["obs"]))
    np.testing.assert_allclose(ppo.log_prob(logits, jnp.asarray(traj["action"])), traj["log_prob"], atol=2e-5)


def test_step_learns_from_its_own_rollout(start):
    """`ppo_step`'s chunk is the rollout's; with the learning rate at 0 every update is on-policy
    (ratio 1: approx_kl 0, clip_frac 0, policy loss 0: the recorded log-probs are the network's
    on the recorded samples) and the value loss is half the mean squared GAE advantage (the
    targets are advantages plus values); with the default rate (the same compiled program) the
    policy moves."""
    g, env_params, hp, state = start
    rolled, traj, last_value = _rollout(ARCH, g, CFG, state, env_params)
    adv = ppo.gae(traj["reward"], traj["value"], traj["done"], last_value, hp.gamma, hp.gae_lambda)
    logits, _ = ppo.policy_value(ARCH, state.params, traj["obs"])

    frozen = hp.replace(opt=hp.opt.replace(lr=jnp.zeros(())))
    new, metrics = _ppo_step(ARCH, g, CFG, _copy(state), frozen, env_params)
    jax.tree.map(np.testing.assert_array_equal, new.params, state.params)
    np.testing.assert_allclose(new.games.obs, rolled.games.obs, rtol=1e-5, atol=1e-6)
    assert int(new.step) == 1
    terms = metrics["terms"]
    assert abs(float(terms["approx_kl"])) < 1e-6 and float(terms["clip_frac"]) == 0.0
    assert abs(float(terms["policy_loss"])) < 1e-5
    np.testing.assert_allclose(terms["value_loss"], 0.5 * np.mean(np.square(adv)), rtol=1e-4)
    np.testing.assert_allclose(terms["entropy"], np.mean(ppo.entropy(logits)), rtol=1e-5)
    np.testing.assert_allclose(metrics["loss"], 0.5 * terms["value_loss"] - 0.01 * terms["entropy"], rtol=1e-4)
    np.testing.assert_allclose(metrics["reward"], np.mean(traj["reward"]), rtol=1e-6)
    np.testing.assert_allclose(metrics["action_mean"], np.mean(traj["action"], axis=(0, 1)), rtol=1e-6)
    assert int(metrics["episodes"]) == int(np.sum(traj["done"]))
    assert metrics["ratios"].shape == (len(jax.tree.leaves(state.params)),)
    assert bool(metrics["finite"]) and not bool(metrics["diverged"])

    moved, metrics = _ppo_step(ARCH, g, CFG, _copy(state), hp, env_params)
    assert float(metrics["terms"]["approx_kl"]) > 1e-7
    assert not np.array_equal(moved.params["policy"]["kernel"], state.params["policy"]["kernel"])
    assert float(metrics["max_ratio"]) > 0 and not bool(metrics["diverged"])
    np.testing.assert_allclose(metrics["reward"], np.mean(traj["reward"]), rtol=1e-6)  # the same chunk


def test_hparams_are_traced_so_a_vmap_sweeps_them(start):
    """A stack of two settings (and of two states) through one `vmap` of the step (traced only)."""
    g, env_params, _, state = start
    hps = jax.tree.map(lambda *x: jnp.stack(x), PPOHParams.create(lr=1e-4, gamma=0.9, entropy_coef=0.0),
                       PPOHParams.create(lr=1e-3, gamma=0.99, entropy_coef=0.01))
    states = jax.tree.map(lambda x: jnp.stack([x, x]), state)
    out, metrics = jax.eval_shape(jax.vmap(lambda s, h: PPO(ARCH, g, CFG, h, env_params).train_step(s)), states, hps)
    assert metrics["loss"].shape == (2,) and metrics["action_mean"].shape == (2, 3)
    assert out.games.obs.shape == (2,) + state.games.obs.shape


def test_policy_presses_by_probability():
    """Greedy presses exactly the buttons with probability > 0.5; sampling presses each with its
    probability."""
    params = ppo.init_params(ARCH, jax.random.PRNGKey(1), 8)
    params["policy"] = {"kernel": jnp.zeros((8, 3)), "bias": jnp.asarray([4.0, -4.0, 0.0])}
    obs = jnp.zeros((150, 150))
    greedy, sampled = ppo.ppo_policy(ARCH, params), ppo.ppo_policy(ARCH, params, greedy=False)

    @jax.jit
    def act(keys):
        play = lambda pol: jax.vmap(lambda k: pol[1](k, pol[0](k, pol[2]), obs, pol[2])[0])(keys)  # noqa: E731
        return play(greedy), play(sampled)

    g_actions, s_actions = act(jax.random.split(jax.random.PRNGKey(0), 4000))
    np.testing.assert_array_equal(g_actions, np.tile([1.0, 0.0, 0.0], (4000, 1)))
    np.testing.assert_allclose(np.mean(s_actions, axis=0), [1 / (1 + np.exp(-4)), 1 / (1 + np.exp(4)), 0.5], atol=0.03)


def test_ppo_learns_a_trivially_learnable_reward(start):
    """With a bonus for turning left, a few dozen PPO updates teach the policy to turn left: its
    greedy return on held-out seeds clearly beats the uniform-random policy's."""
    from cdrl.evaluation import play
    from envs.policies import get_policy

    g, env_params, hp, state = start
    state = _copy(state)
    for _ in range(30):
        state, metrics = _ppo_step(ARCH, g, CFG, state, hp, env_params)
    assert not bool(metrics["diverged"])
    assert float(metrics["action_mean"][1]) > 0.9 and float(metrics["action_mean"][0]) < 0.1
    seeds = np.arange(1000, 1016)
    init, step, p = ppo.ppo_policy(ARCH, state.params)
    learned = play.summarize(*play.play(g, env_params, init, step, seeds, 40, params=p))
    uniform = get_policy("uniform")
    random = play.summarize(*play.play(g, env_params, uniform.init, uniform.step, seeds, 40))
    assert learned["ci95"][0] > random["ci95"][1] + 5.0, (learned, random)


@pytest.mark.parametrize("field", ["num_envs", "unroll", "epochs", "minibatches", "hidden"])
def test_bad_config_values_are_refused(field):
    with pytest.raises(ValueError, match=field):
        PPOConfig(**{field: 0})


def test_bad_minibatches_and_hparams_are_refused():
    with pytest.raises(ValueError, match=r"num_envs \* unroll \(3 \* 5 = 15\).*minibatches \(4\)"):
        PPOConfig(num_envs=3, unroll=5, minibatches=4)
    with pytest.raises(ValueError, match="num_envs"):
        PPOConfig(num_envs=2.5)
    for field, value in [("gamma", 1.5), ("gae_lambda", -0.1), ("clip_eps", 0.0), ("entropy_coef", -1.0),
                         ("value_coef", -0.5), ("lr", 0.0)]:
        with pytest.raises(ValueError, match=field):
            PPOHParams.create(**{field: value})
