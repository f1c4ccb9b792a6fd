"""`mpc_planner`: model-predictive control through the world model (TD-MPC2's planning, with
the buttons' eight combinations as the candidates).

Each step, from the model's state before the real frame o_t, every candidate plan is scored: one
of the eight button combinations pressed with o_t (the model's real step) and held `horizon` − 1
imagined steps more. A plan's score is its discounted return, as the model predicts it, plus the
discounted value at its end (`imagined_return`). The buttons pressed at t are the best plan's,
each drawn uniformly with the exploration ε. There is no step of delay: the planner sees o_t
before it chooses a_t.

The world model learns from the replay buffer as every replay learner's does. With the
look-ahead (`--lookahead-steps K`) its reward head scores the imagined steps and its value
head, fitted to real λ-returns, ends them; without, the variant's own reward scores them and
no value ends them. The controller head D_a is not trained: the planner is the policy.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from cdrl.data.frames import model_obs
from cdrl.learners.game_batch import Observation
from cdrl.learners.imagination import imagination_config, imagined_return, lookahead_heads
from cdrl.learners.replay_base import ReplayLearner, ReplayState, draw_buttons
from cdrl.models.base import BUTTON_COMBOS, StepInput, Variant
from cdrl.training import lookahead

# A tie between plans (an untrained model scores every plan alike) is broken at random.
JITTER = 1e-6


def plan_rollouts(variant: Variant, params, carry, x: StepInput, horizon: int, last_frame: bool = False):
    """Every candidate plan for the real step `x` (B games: the frames o_t, `is_first`; its
    action is ignored) from the model's state `carry` before it. A plan is one of the eight
    button combinations (`BUTTON_COMBOS`) pressed at t with o_t and held `horizon` − 1 imagined
    steps more. Returns the variant's rewards `[C, H, B]`, the states' features `[C, H, B, F]`
    after each of a plan's steps, and the frame predicted after its last step `[C, B, H, W]`.
    That frame is decoded where the variant imagines without it only with `last_frame`."""
    b = x.obs.shape[0]

    def rollout(buttons):
        action = jnp.broadcast_to(buttons, (b, buttons.shape[-1]))
        first, out = variant.step(params, carry, x.replace(action=action))

        def body(c, _):
            carry, frame = c
            carry, out = variant.imagine_step(params, carry, frame, action)
            if "logits" in out:
                frame = jax.nn.sigmoid(out["logits"])
            elif last_frame:
                frame = jax.nn.sigmoid(variant.decode(params, out["pred_code"]))
            return (carry, frame), (out["reward"], variant.features(carry))

        (_, last), (rewards, h) = jax.lax.scan(body, (first, jax.nn.sigmoid(out["logits"])), None,
                                               length=horizon - 1)
        return (jnp.concatenate([out["reward"][None], rewards]),
                jnp.concatenate([variant.features(first)[None], h]), last)

    return jax.vmap(rollout)(jnp.asarray(BUTTON_COMBOS))


def plan_scores(variant: Variant, look, params, carry, x: StepInput, gamma, horizon: int):
    """`[B, C]`: the plans of `plan_rollouts` scored by their discounted return plus the
    discounted value at their end (`imagined_return`; `look`, the look-ahead's numbers, or
    None). With a frame value head, it values the plan's last predicted frame. With an
    advantage head the plans are one step (`horizon` 1), each scored by the advantage A(h)."""
    heads = lookahead_heads(look, params)
    if heads is not None and look.advantage:  # one-step plans, ranked by the advantage of their buttons
        return lookahead.advantage(heads, plan_rollouts(variant, params, carry, x, 1)[1][:, 0]).T
    valued = heads is not None and look.frame_value
    rewards, h, last = plan_rollouts(variant, params, carry, x, horizon, last_frame=valued)
    if valued:
        ends = lookahead.frame_value(heads, last, variant.arch, look)  # [C, B]
        return jax.vmap(lambda r, f, e: imagined_return(look, params, r, f, gamma, e))(rewards, h, ends).T
    return jax.vmap(lambda r, f: imagined_return(look, params, r, f, gamma))(rewards, h).T


def plan(variant: Variant, look, params, carry, x: StepInput, gamma, horizon: int, key):
    """The plans of `plan_rollouts` scored (`plan_scores`). Returns the scores `[B, C]` and the
    best plan's buttons `[B, A]`, the ones to press now."""
    scores = plan_scores(variant, look, params, carry, x, gamma, horizon)
    best = jnp.argmax(scores + JITTER * jax.random.uniform(key, scores.shape), axis=-1)
    return scores, jnp.asarray(BUTTON_COMBOS)[best]


@functools.lru_cache(maxsize=32)
def planner_fns(variant: Variant, horizon: int):
    """(init, step) of the noise-free planner for one game, in the form of
    `cdrl.evaluation.play`; its parameters are `{"model", "look", "gamma"}`. Its state keeps
    the plans' `scores` of its last step (`cdrl.analysis.policy_video` shows them). One pair per
    variant and horizon, so a program playing it compiles once for any parameters."""

    def init(key, params):
        del key, params
        return {"carry": variant.init_carry(1), "is_first": jnp.ones((1,), bool),
                "scores": jnp.zeros((1, len(BUTTON_COMBOS)))}

    def step(key, state, obs, params):
        x = StepInput(obs=model_obs(obs, variant.arch)[None], action=jnp.zeros((1, variant.arch.action_dim)),
                      is_first=state["is_first"])
        scores, best = plan(variant, params["look"], params["model"], state["carry"], x, params["gamma"], horizon,
                            key)
        carry, _ = variant.step(params["model"], state["carry"], x.replace(action=best))
        return best[0], {"carry": carry, "is_first": jnp.zeros((1,), bool), "scores": scores}

    return init, step


def game_plans(game, env_params, state, horizon: int, key):
    """The plans of `plan_rollouts` played in the true game from its state `state`: each button
    combination held `horizon` steps, the plans sharing their keys. Returns the game's states at
    their ends `[C, ...]`, whether each game is still on there `[C]` and the rewards `[H, C]`
    (zero after the game's end)."""
    combos = jnp.asarray(BUTTON_COMBOS)

    def held(c, k):
        s, on = c
        s, reward, term, trunc, _ = jax.vmap(game.step_state, (None, 0, 0, None))(k, s, combos, env_params)
        return (s, on & ~(term | trunc)), reward * on

    states = jax.tree.map(lambda x: jnp.broadcast_to(x, combos.shape[:1] + x.shape), state)
    (ends, on), rewards = jax.lax.scan(held, (states, jnp.ones(combos.shape[0], bool)), jax.random.split(key, horizon))
    return ends, on, rewards


def oracle_planner(game, policy, gamma: float, horizon: int, *, samples: int = 4, steps: int = 30):
    """The planner with a perfect model and a perfect value of `policy`, as a privileged policy
    (its step reads the game's state; `cdrl.evaluation.play`). Each step it holds every button
    combination `horizon` steps in the true game, adds γ^horizon times `policy`'s value there
    (`probe_ceiling.policy_value`, `samples` plays of `steps` steps) and presses the best plan's
    first buttons at once (no step of delay; a tie goes to the first combination, straight on).
    The plans of one step share their keys. It bounds what `MPCPlanner` can reach with a value
    of `policy`: the model and the value are the only things it replaces."""
    from cdrl.evaluation.probe_ceiling import policy_value
    from envs.policies import Policy, uniform_init  # not at import: its module makes arrays, and
    # `cdrl train` must reach `jax.distributed.initialize` before the backend starts

    discounts = gamma ** jnp.arange(horizon, dtype=jnp.float32)

    def step(key, ps, obs, state, env_params):
        del obs
        k_plan, k_value = jax.random.split(key)
        ends, on, rewards = game_plans(game, env_params, state, horizon, k_plan)
        value = policy_value(game, env_params, policy, gamma, k_value, ends, on, samples=samples, steps=steps)
        return jnp.asarray(BUTTON_COMBOS)[jnp.argmax(discounts @ rewards + gamma ** horizon * value)], ps

    return Policy(f"oracle_planner({policy.name}, H {horizon})", uniform_init, step, privileged=True)


class MPCPlanner(ReplayLearner):
    """See the module docstring. `model` is a controller variant that predicts reward."""

    name = "mpc_planner"
    row = "planner"
    act_terms = ("plan_spread",)

    @classmethod
    def from_run(cls, cfg, model, game, env_params):
        return cls(model, game, imagination_config(cfg), cls.hparams(cfg, model), env_params)

    def act(self, state: ReplayState, obs: Observation, key: jax.Array, explore=None):
        """Plan from o_t and press the best plan's first buttons at once, each drawn uniformly
        with chance ε; the model then sees o_t and them. `info`: the model's outputs and
        `plan_spread`, the best plan's score minus the worst's. `state.action` keeps the buttons
        pressed."""
        explore = self.exploration(state) if explore is None else explore
        params = state.model.params
        x = StepInput(obs=obs.frames, action=state.action, is_first=obs.is_first)
        k_plan, k_draw = jax.random.split(key)
        scores, best = plan(self.model, self.hp.model.lookahead, params, state.model.carry, x, self.hp.gamma,
                            self.config.horizon, k_plan)
        executed = draw_buttons(k_draw, (1.0 - explore) * best + explore * 0.5)
        carry, out = self.model.step(params, state.model.carry, x.replace(action=executed))
        state = state.replace(model=state.model.replace(carry=carry), action=executed)
        return state, executed, {**out, "plan_spread": jnp.max(scores, -1) - jnp.min(scores, -1)}

    def policy(self, state: ReplayState):
        init, step = planner_fns(self.model, self.config.horizon)
        return init, step, {"model": state.model.params, "look": self.hp.model.lookahead, "gamma": self.hp.gamma}
