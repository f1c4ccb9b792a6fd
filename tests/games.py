"""The small games the training tests play, built once per process: the same instance every
call, so that programs taking the game as a static argument compile once."""
import functools

import jax.numpy as jnp
import numpy as np

from envs.slither import Slither

SIZES = {"num_opponents": 2, "max_segments": 16, "arena_size": 1000.0}
MAX_STEPS = 40


class LeftBonusSlither(Slither):
    """The game with a reward of 1 more for every step that turns left (left pressed, right
    not): a reward any controller can learn."""

    def step_state(self, key, state, action, params=None):
        state, reward, terminated, truncated, info = super().step_state(key, state, action, params)
        pressed = jnp.asarray(action) > 0.5
        return state, reward + (pressed[1] & ~pressed[0]), terminated, truncated, info


class TurnOneSlither(Slither):
    """The test game without its rewards or an end: 1 for every step that presses turn button 1
    alone, else 0. From any state, holding turn button 1 for k steps returns k, the other
    sequences 0 (the imagination probe's steering sequences)."""

    def step_state(self, key, state, action, params=None):
        state, _, _, _, info = super().step_state(key, state, action, params)
        pressed = jnp.asarray(action) > 0.5
        never = jnp.array(False)
        return state, (pressed[1] & ~pressed[0]).astype(jnp.float32), never, never, info


@functools.cache
def test_game():
    """(game, params): 2 opponents, 16 segments, a 1000-pixel arena, episodes cut at 40 steps."""
    g = Slither(**SIZES)
    return g, g.default_params.replace(max_steps=np.int32(MAX_STEPS))


@functools.cache
def left_bonus_game():
    """(game, params): `test_game` with the left-turn bonus (`LeftBonusSlither`)."""
    g = LeftBonusSlither(**SIZES)
    return g, g.default_params.replace(max_steps=np.int32(MAX_STEPS))


def learned_and_random(learner, state, seeds):
    """The `play.summarize` rows of the learner's noise-free policy and of the uniform-random
    policy on the games `seeds` of the learner's game, each at most `MAX_STEPS` steps."""
    from cdrl.evaluation import play
    from envs.policies import get_policy

    g, params = learner.game, learner.env_params
    init, step, p = learner.policy(state)
    learned = play.summarize(*play.play(g, params, init, step, seeds, MAX_STEPS, params=p))
    uniform = get_policy("uniform")
    return learned, play.summarize(*play.play(g, params, uniform.init, uniform.step, seeds, MAX_STEPS))


# Not tests themselves, though a test module that imports them by name would collect them.
test_game.__test__ = False
left_bonus_game.__test__ = False
learned_and_random.__test__ = False
