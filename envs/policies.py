"""The thesis's data-collection policies as pure functions (usable inside ``lax.scan``).

Every policy is a pair ``init(key) -> policy_state`` and
``step(key, policy_state, obs) -> (action, policy_state)``; the action is 3 float32
values in [0, 1] (turn right, turn left, accelerate; > 0.5 = pressed) and is what a
data set records.  Observations are accepted but unused (both policies are blind).
Random numbers come from :mod:`envs.fastrng` (cheap on CPU inside ``lax.scan``).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import struct

from envs import fastrng

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


@dataclasses.dataclass(frozen=True)
class Policy:
    """A named pure policy: ``init(key)`` and ``step(key, state, obs)``."""

    name: str
    init: Callable[[jax.Array], Any]
    step: Callable[..., tuple[jnp.ndarray, Any]]


POLICIES: dict[str, Policy] = {
    "behaviour": Policy("behaviour", behaviour_init, behaviour_step),
    "uniform": Policy("uniform", uniform_init, uniform_step),
}


def get_policy(name: str) -> Policy:
    """The policy called ``name`` ("behaviour" or "uniform")."""
    try:
        return POLICIES[name]
    except KeyError:
        raise ValueError(f"unknown policy {name!r}; choose one of {sorted(POLICIES)}") from None
