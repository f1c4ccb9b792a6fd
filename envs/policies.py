"""The game's scripted policies as pure functions (usable inside ``lax.scan``): the thesis's
two data-collection policies, and the reference policies a learned controller is measured
against.

Every policy is a pair ``init(key) -> policy_state`` and
``step(key, policy_state, obs) -> (action, policy_state)``; the action is 3 float32
values in [0, 1] (turn right, turn left, accelerate; > 0.5 = pressed) and is what a
data set records.  The blind policies accept observations and ignore them:

- ``behaviour``: the thesis's behaviour switching (observation data; never accelerates);
- ``uniform``: three values uniform in [0, 1] (action data; accelerates half the time, and
  accelerating costs length every step);
- ``held_uniform``: ``uniform``'s buttons, each draw held for a while: new buttons with
  probability ``HOLD_SWITCH_PROB`` a step, so a draw lasts 5 steps on average (action data
  whose button sequences last as long as a planner's do);
- ``never_accelerate``: uniform random turning, accelerate never pressed. Since
  accelerating costs length, this is the floor a controller must beat to show control:
  learning "never accelerate" alone reaches it.

:func:`privileged_policy` is different in kind: its ``step`` also takes the game's state
(``step(key, policy_state, obs, game_state, params)``) and steers by the true positions of pellets
and opponents, which a pixel controller never sees. It is the upper reference.
Random numbers come from :mod:`envs.fastrng` (cheap on CPU inside ``lax.scan``).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import struct

from envs import fastrng
from envs.render import wrap_delta

BEHAVIOURS = jnp.asarray(
    [
        [0.0, 0.0, 0.0],  # straight
        [1.0, 0.0, 0.0],  # right
        [0.0, 1.0, 0.0],  # left
        [1.0, 1.0, 0.0],  # slither (right + left)
    ],
    jnp.float32,
)
"""The 4 behaviours of the behaviour-switching policy, one action row each."""

SWITCH_PROB = 0.01
HOLD_SWITCH_PROB = 0.2  # held_uniform: the chance of new buttons each step (a draw lasts 5 steps on average)


@struct.dataclass
class BehaviourState:
    """State of the behaviour-switching policy: index into :data:`BEHAVIOURS`."""

    behaviour: jnp.ndarray


@struct.dataclass
class UniformState:
    """State of the uniform policy (it has none; a placeholder scalar)."""

    unused: jnp.ndarray


def behaviour_init(key: jax.Array) -> BehaviourState:
    """Starts with a behaviour drawn uniformly from the 4."""
    u = fastrng.uniform(key, 1)[0]
    return BehaviourState(behaviour=jnp.minimum((u * 4).astype(jnp.int32), 3))


def behaviour_step(key: jax.Array, state: BehaviourState, obs: Any = None,
                   switch_prob: float = SWITCH_PROB):
    """With probability ``switch_prob`` pick a new behaviour uniformly (possibly the
    same one), then act it out.  Never accelerates.

    Returns ``(action [3] float32, new state)``.
    """
    u = fastrng.uniform(key, 2)
    switch = u[0] < switch_prob
    pick = jnp.minimum((u[1] * 4).astype(jnp.int32), 3)
    behaviour = jnp.where(switch, pick, state.behaviour)
    return BEHAVIOURS[behaviour], BehaviourState(behaviour=behaviour)


def uniform_init(key: jax.Array) -> UniformState:
    """The uniform policy's (empty) state."""
    return UniformState(unused=jnp.zeros((), jnp.float32))


def uniform_step(key: jax.Array, state: UniformState, obs: Any = None):
    """Three values uniform in [0, 1]; each is performed when > 0.5.

    Returns ``(action [3] float32, state)``.
    """
    return fastrng.uniform(key, 3), state


@struct.dataclass
class HeldState:
    """State of the held-uniform policy: the buttons being held, [3]."""

    action: jnp.ndarray


def held_uniform_init(key: jax.Array) -> HeldState:
    """Starts holding uniform buttons."""
    return HeldState(action=fastrng.uniform(key, 3))


def held_uniform_step(key: jax.Array, state: HeldState, obs: Any = None, switch_prob: float = HOLD_SWITCH_PROB):
    """With probability ``switch_prob`` draw new uniform buttons, then press the held ones.

    Returns ``(action [3] float32, new state)``.
    """
    u = fastrng.uniform(key, 4)
    action = jnp.where(u[0] < switch_prob, u[1:], state.action)
    return action, HeldState(action=action)


def never_accelerate_step(key: jax.Array, state: UniformState, obs: Any = None):
    """Right and left each pressed with probability 1/2, accelerate never.

    Returns ``(action [3] float32, state)``.
    """
    u = fastrng.uniform(key, 2)
    return jnp.concatenate([u, jnp.zeros((1,), jnp.float32)]), state


SELDOM_ACCELERATE = 0.1  # seldom_accelerate: the chance of pressing accelerate each step


def seldom_accelerate_step(key: jax.Array, state: UniformState, obs: Any = None):
    """Right and left each pressed with probability 1/2, accelerate with probability
    ``SELDOM_ACCELERATE``: a never-accelerating play whose data still show every button.

    Returns ``(action [3] float32, state)``.
    """
    u = fastrng.uniform(key, 3)
    return jnp.concatenate([u[:2], (u[2:] < SELDOM_ACCELERATE).astype(jnp.float32)]), state


def random_turns_instead(key: jax.Array, buttons: jax.Array, share) -> jax.Array:
    """``buttons`` [3], or with probability ``share`` random turns in their place (right and left
    each pressed with probability 1/2, accelerate never; 0/1 floats): the exploration that puts
    recoveries into a scripted policy's data."""
    k_turn, k_swap = jax.random.split(key)
    turns = (jax.random.uniform(k_turn, (3,)) < 0.5).astype(jnp.float32) * jnp.array([1.0, 1.0, 0.0])
    return jnp.where(jax.random.uniform(k_swap) < share, turns, buttons)


@dataclasses.dataclass(frozen=True)
class Policy:
    """A named pure policy: ``init(key)`` and ``step(key, state, obs)``; a ``privileged``
    one's step takes the game's state and physics too: ``step(key, state, obs, game_state,
    params)``."""

    name: str
    init: Callable[[jax.Array], Any]
    step: Callable[..., tuple[jnp.ndarray, Any]]
    privileged: bool = False


POLICIES: dict[str, Policy] = {
    "behaviour": Policy("behaviour", behaviour_init, behaviour_step),
    "uniform": Policy("uniform", uniform_init, uniform_step),
    "held_uniform": Policy("held_uniform", held_uniform_init, held_uniform_step),
    "never_accelerate": Policy("never_accelerate", uniform_init, never_accelerate_step),
    "seldom_accelerate": Policy("seldom_accelerate", uniform_init, seldom_accelerate_step),
}

# How far ahead (raw pixels) and how wide a corridor the privileged policy checks for
# opponents' bodies before it steers to a pellet.
DANGER_AHEAD = 60.0
DANGER_WIDTH = 24.0


@functools.lru_cache(maxsize=16)
def privileged_policy(game) -> Policy:
    """The privileged scripted policy of ``game`` (one per game, so that the programs playing
    it compile once): it reads the game's state (positions of every pellet and opponent segment) and, each step,

    1. turns away from the nearest opponent segment inside the corridor ``DANGER_AHEAD``
       pixels ahead and ``DANGER_WIDTH`` wide (away from the side it lies on);
    2. otherwise steers to the reachable pellet it reaches first: the time to turn to it at
       ``turn_rate`` per step plus the time to cover the distance at ``speed``; a pellet
       inside either turning circle (radius ``speed / turn_rate``) cannot be reached by
       turning and is skipped;
    3. never accelerates.

    It sees what no pixel controller does, so it is the upper reference, not a competitor.
    """
    cs, g, arena = game.pellet_cell_size, game.grid, game.arena_size

    def step(key, state, obs, game_state, params):
        del key, obs
        hx, hy, heading = game_state.x[0, 0], game_state.y[0, 0], game_state.heading[0]
        c, s = jnp.cos(heading), jnp.sin(heading)

        def heading_frame(x, y):
            """(ahead, to the right) of points relative to the head; y grows downwards."""
            dx, dy = wrap_delta(x - hx, arena), wrap_delta(y - hy, arena)
            return dx * c + dy * s, -dx * s + dy * c

        cells = jnp.arange(g, dtype=jnp.float32) * cs
        ahead, right = heading_frame(cells[None, :] + game_state.pellet_dx, cells[:, None] + game_state.pellet_dy)
        radius = params.speed / params.turn_rate
        inside = jnp.minimum(jnp.hypot(ahead, right - radius), jnp.hypot(ahead, right + radius)) < radius
        angle = jnp.arctan2(right, ahead)
        cost = jnp.abs(angle) / params.turn_rate + jnp.hypot(ahead, right) / params.speed
        cost = jnp.where((game_state.pellet_value > 0) & ~inside, cost, jnp.inf)
        target = jnp.argmin(cost)
        target_angle = jnp.where(jnp.isfinite(cost.reshape(-1)[target]), angle.reshape(-1)[target], 0.0)
        steer = jnp.sign(target_angle) * (jnp.abs(target_angle) > params.turn_rate / 2)

        o_ahead, o_right = heading_frame(game_state.x[1:], game_state.y[1:])
        active = game.active(game_state)[1:]
        danger = active & (o_ahead > 0) & (o_ahead < DANGER_AHEAD) & (jnp.abs(o_right) < DANGER_WIDTH)
        nearest = jnp.argmin(jnp.where(danger, o_ahead, jnp.inf))
        away = -jnp.sign(o_right.reshape(-1)[nearest] + 1e-6)
        turn = jnp.where(jnp.any(danger), away, steer)
        action = jnp.stack([turn > 0, turn < 0, jnp.zeros((), bool)]).astype(jnp.float32)
        return action, state

    return Policy("privileged", uniform_init, step, privileged=True)


def get_policy(name: str) -> Policy:
    """The blind policy called ``name`` (one of :data:`POLICIES`)."""
    try:
        return POLICIES[name]
    except KeyError:
        raise ValueError(f"unknown policy {name!r}; choose one of {sorted(POLICIES)}") from None
