"""`onpolicy_ac`'s critic plan: one step of look-ahead through the model, scored by the predicted
reward and the critic, tilting the controller's buttons. Its pieces against written-out loops
and the product of independent buttons; its choices at the two ends of κ; the draws of training
against the distribution they come from; a reward it learns."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import games
from cdrl.learners import onpolicy_ac as oac
from cdrl.learners import replay_base as rb
from cdrl.learners.api import train_program
from cdrl.learners.game_batch import observe
from cdrl.models import make_variant, nets
from cdrl.models.arch import TINY
from cdrl.models.base import BUTTON_COMBOS, StepInput
from cdrl.runs.config import RunConfig
from cdrl.training.optim import HParams, OptHParams

COMBOS = np.asarray(BUTTON_COMBOS, np.float32)


def _model_and_state(batch=3, seed=0):
    """A tiny final_proposal model, a critic, and the model's state after two random frames."""
    v = make_variant("final_proposal", TINY)
    k = jax.random.split(jax.random.PRNGKey(seed), 5)
    params = v.init(k[0])
    critic = nets.init_mlp(k[1], (v.arch.lstm_size, rb.CRITIC_HIDDEN, 1), final_selu=False)
    carry = v.init_carry(batch)
    s = v.arch.image_size
    for i, key in enumerate(k[2:4]):
        x = StepInput(obs=jax.random.uniform(key, (batch, s, s)), action=jnp.full((batch, 3), 0.5 * i),
                      is_first=jnp.full((batch,), i == 0))
        carry, _ = v.step(params, carry, x)
    x = StepInput(obs=jax.random.uniform(k[4], (batch, s, s)), action=jnp.zeros((batch, 3)),
                  is_first=jnp.zeros((batch,), bool))
    return v, params, critic, carry, x


def test_plan_values_are_one_model_step_and_the_critic_per_combination():
    """Q(a) = r̂(a) + γ V(h_t(a)): each combination pressed with the real frame, one model step,
    written out as a loop over the eight."""
    v, params, critic, carry, x = _model_and_state()
    gamma = 0.9
    q = np.asarray(oac.plan_values(v, params, critic, carry, x, gamma))
    assert q.shape == (3, len(COMBOS))
    for c, buttons in enumerate(COMBOS):
        after, out = v.step(params, carry, x.replace(action=jnp.broadcast_to(buttons, (3, 3))))
        expected = out["reward"] + gamma * rb.critic_value(critic, v.features(after))
        np.testing.assert_allclose(q[:, c], np.asarray(expected), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("explore", [0.0, 0.3])
def test_prior_log_probs_are_independent_buttons(explore):
    """log π(a) is the sum of each button's log-probability under the controller's output (mixed
    with a uniform draw at ε), and the eight combinations' probabilities add up to one."""
    v, params, _, carry, _ = _model_and_state()
    logp = np.asarray(oac.prior_log_probs(v, params, carry, explore))
    p = np.asarray(v.heads(params, v.fc(params, v.features(carry)))["action"], np.float64)
    p = (1 - explore) * p + explore * 0.5
    by_hand = np.log(np.prod(np.where(COMBOS[None] > 0.5, p[:, None], 1 - p[:, None]), axis=-1))
    np.testing.assert_allclose(logp, by_hand, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(np.exp(logp).sum(-1), 1.0, rtol=1e-5)


def test_the_noise_free_plan_presses_the_best_plan_or_the_controllers_buttons():
    """At a large κ the policy presses the combination of the highest Q; at κ 0 the controller's
    buttons (each pressed when its probability passes one half); at an episode's first frame
    nothing. Played in the form of `cdrl.evaluation.play` (one game)."""
    v, params, critic, carry, x = _model_and_state(batch=1)
    init, step = oac.critic_plan_fns(v)
    gamma = jnp.float32(0.9)
    obs = x.obs[0]  # the model's frame: `model_obs` leaves a frame of the model's size as it is
    state = {"carry": carry, "is_first": jnp.zeros((1,), bool)}
    q = np.asarray(oac.plan_values(v, params, critic, carry, x, gamma))[0]
    probs = np.asarray(v.heads(params, v.fc(params, v.features(carry)))["action"])[0]
    for kappa, expected in ((1e6, COMBOS[np.argmax(q)]), (0.0, (probs > 0.5).astype(np.float32))):
        theirs = {"model": params, "critic": critic, "gamma": gamma, "kappa": jnp.float32(kappa)}
        pressed, new = step(jax.random.PRNGKey(0), state, obs, theirs)
        np.testing.assert_array_equal(np.asarray(pressed), expected)
        assert not bool(new["is_first"][0])
    first, _ = step(jax.random.PRNGKey(0), init(None, None), obs, theirs)
    np.testing.assert_array_equal(np.asarray(first), np.zeros(3))


def _learner(critic_plan: str, plan_weight: float = 30.0):
    g, params = games.left_bonus_game()
    v = make_variant("final_proposal", TINY)
    cfg = oac.OnPolicyConfig(num_envs=8, unroll=8, replay=16, model_updates=2, critic_plan=critic_plan)
    hp = rb.ReplayHParams.create(HParams.create(v, opt=OptHParams.create(lr=0.1, momentum=0.9)), warmup_steps=5,
                                 ctrl_opt=OptHParams.create("adam", lr=1e-3), ascent=1.0, gamma=0.95, entropy=3e-3,
                                 plan_weight=plan_weight)
    learner = oac.OnPolicyAC(v, g, cfg, hp, params)
    return learner, learner.init(jax.random.PRNGKey(0))


def test_training_draws_from_the_tilted_controller():
    """With `always` the buttons of training are drawn from π_ε(a) exp(κ Q(a)): over many draws
    from one state, each combination's frequency matches that distribution, written out from
    `prior_log_probs` and `plan_values`; at an episode's first frame nothing is pressed."""
    learner, state = _learner("always", plan_weight=20.0)
    v, explore = learner.model, 0.3
    obs = observe(state.games)
    obs = obs._replace(is_first=jnp.zeros_like(obs.is_first))
    params, carry = state.model.params, state.model.carry
    x = StepInput(obs=obs.frames, action=state.action, is_first=obs.is_first)
    logits = (np.asarray(oac.prior_log_probs(v, params, carry, explore), np.float64)
              + 20.0 * np.asarray(oac.plan_values(v, params, state.critic, carry, x, 0.95), np.float64))
    expected = np.exp(logits - logits.max(-1, keepdims=True))
    expected /= expected.sum(-1, keepdims=True)
    n = 4000
    executed = jax.jit(jax.vmap(lambda k: learner.act(state, obs, k, explore)[1]))(
        jax.random.split(jax.random.PRNGKey(1), n))  # [n, B, 3]
    index = np.asarray(executed) @ np.array([1, 2, 4])  # a combination's index, its buttons as bits
    order = np.asarray(COMBOS) @ np.array([1, 2, 4])
    freq = np.stack([(index == i).mean(0) for i in order], -1)  # [B, C] in BUTTON_COMBOS's order
    assert np.max(np.abs(freq - expected)) < 0.035, (freq, expected)
    first = obs._replace(is_first=jnp.ones_like(obs.is_first))
    _, pressed, _ = learner.act(state, first, jax.random.PRNGKey(2), explore)
    np.testing.assert_array_equal(np.asarray(pressed), 0.0)


def test_the_plan_is_onpolicy_acs_and_a_known_choice():
    """Another learner, or a plan not in `CRITIC_PLANS`, is refused by name; κ below 0 too."""
    with pytest.raises(ValueError, match="critic_plan"):
        RunConfig(variant="final_proposal", learner="mpc_planner", critic_plan="eval")
    with pytest.raises(ValueError, match="critic_plan"):
        RunConfig(variant="final_proposal", learner="onpolicy_ac", critic_plan="sometimes")
    with pytest.raises(ValueError, match="plan_weight"):
        RunConfig(variant="final_proposal", learner="onpolicy_ac", critic_plan="eval", plan_weight=-1.0)
    cfg = RunConfig(variant="final_proposal", learner="onpolicy_ac", critic_plan="always", plan_weight=30.0)
    assert cfg.to_dict()["control"]["critic_plan"] == "always"
    with pytest.raises(ValueError, match="critic_plan"):
        dataclasses.replace(oac.OnPolicyConfig(), critic_plan="x")


@pytest.mark.e2e
def test_the_critic_plan_learns_a_trivially_learnable_reward():
    """With a bonus for turning left, `onpolicy_ac` playing its critic plan in training too
    learns to turn left: its noise-free plan on held-out seeds clearly beats random play. (At κ
    300 it explores too little to find the bonus: +0.56 against random's +6.08.)"""
    learner, state = _learner("always", plan_weight=30.0)
    for _ in range(60):
        state, metrics = train_program(learner, state)
    assert float(metrics["controller_on"]) == 1.0 and not bool(metrics["diverged"])
    learned, random = games.learned_and_random(learner, state, np.arange(1000, 1016))
    assert learned["ci95"][0] > random["ci95"][1] + 5.0, (learned, random)


def test_the_plan_configurations_train_as_the_controller_they_plan_for():
    """The experiment's `real-plan-eval` and `real-plan` are `real-pre-all-open-bal` with the
    critic plan: the same pre-training and the same options but the plan's two."""
    from experiments.controller import study

    budget = study.BUDGETS["48k"]
    base = dataclasses.asdict(study.config_of("real-pre-all-open-bal", budget, 3))
    for name in ("real-plan-eval", "real-plan"):
        assert study.pretrain_config(name, budget, 3) == study.pretrain_config("real-pre-all-open-bal", budget, 3)
        mine = dataclasses.asdict(study.config_of(name, budget, 3))
        differ = {k for k in mine if mine[k] != base[k]}
        assert "critic_plan" in differ and differ <= {"critic_plan", "plan_weight"}, differ
