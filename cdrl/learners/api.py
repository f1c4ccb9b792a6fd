"""The interface every learner that plays the game implements, and the one jitted program of it.

A learner is a pytree (`flax.struct.PyTreeNode`). Its static half is the model it trains (a
variant, or a model-free policy's architecture), the game and its static `config` (shapes,
counts). Its traced half is `hp` (learning rates, discounts, loss weights) and `env_params`
(the game's physics). So one compiled program serves every value of the traced half, and a
`vmap` over a stack of them sweeps it.

What a learner does:

- `init(key) -> state`: fresh parameters, optimiser states and B new games;
- `act(state, obs, key) -> (state, action, info)`: one step of its exploring policy on the B
  games' `Observation`; `action` `[B, A]` is what the games execute now;
- `update(state, batch) -> (state, metrics)`: learn from what `collect` gathered;
- `train_step(state) -> (state, metrics)`: one step of the run's program, `collect` (T steps
  of `act` and the games) then `update`;
- `policy(state)`: the learned policy without exploration, in the form of
  `cdrl.evaluation.play` (`(init, step, params)`);
- `watched(state)`: the parameters whose norm ratios the run logs.

`metrics` hold what the host loop records of every run (`loss`, `terms`, and the divergence
guard's `ratios`, `max_ratio`, `worst_group`, `finite`, `diverged`) and the game's statistics
(`reward`, `episodes`, `return_sum`, `length_sum`, `action_mean`). Names in `extras` are
logged as they are.

`from_run(cfg, model, game, env_params)` builds the learner from a run's config; a learner is
registered under its name in `cdrl.learners` (`register`).
"""
from __future__ import annotations

from typing import Any, Callable, ClassVar

import flax.struct
import jax

from cdrl.learners.game_batch import Observation, observe, step_games


class Learner(flax.struct.PyTreeNode):
    """A learner that plays the game as it learns; see the module docstring."""

    model: Any = flax.struct.field(pytree_node=False)
    game: Any = flax.struct.field(pytree_node=False)
    config: Any = flax.struct.field(pytree_node=False)
    hp: Any = None
    env_params: Any = None

    name: ClassVar[str] = ""
    # The row of its policy in the evaluation table.
    row: ClassVar[str] = "controller"
    # Metrics its records add, logged as they are.
    extras: ClassVar[tuple[str, ...]] = ()
    # Whether it learns a world model (a controller variant's) that `--init-from` can start it
    # from. A learner without one is model-free: it plays whatever the run's variant.
    has_world_model: ClassVar[bool] = True
    # Which overrides of the run's recipe it takes (`cdrl.runs.config.FAMILY_OVERRIDES`): "replay"
    # (a world model teacher-forced from a buffer) or "ascent" (learning online from each chunk
    # once). A model-free learner takes PPO's numbers (`cdrl.runs.config.AGENT_RECIPE`).
    recipe_family: ClassVar[str] = "replay"
    # Whether its program may reuse the state's buffers (the caller keeps no reference).
    donate_state: ClassVar[bool] = True

    @classmethod
    def from_run(cls, cfg, model, game, env_params) -> "Learner":
        """The learner a run of `cfg` (`cdrl.runs.config.RunConfig`) trains."""
        raise NotImplementedError

    def init(self, key: jax.Array):
        raise NotImplementedError

    def act(self, state, obs: Observation, key: jax.Array):
        raise NotImplementedError

    def update(self, state, batch):
        raise NotImplementedError

    def train_step(self, state):
        raise NotImplementedError

    def policy(self, state) -> tuple[Callable, Callable, Any]:
        raise NotImplementedError

    def watched(self, state):
        raise NotImplementedError

    @property
    def arch(self):
        """The architecture of the learner's frames: its variant's, or its own."""
        return getattr(self.model, "arch", self.model)

    def world_model(self, state):
        """The world model's parameters in `state` (controller included)."""
        return self.watched(state)

    def with_world_model(self, state, params):
        """`state` with the world model's parameters `params`."""
        raise NotImplementedError(f"learner {self.name!r} holds no world model")


def collect(learner: Learner, state, length: int):
    """`length` steps of `learner.act` and the B games, for a learner whose state holds its
    `games` and a PRNG `key`. Returns (state after them, records `[length, B, ...]`: the frames
    seen, the actions, what `act` reported, the rewards and the games' statistics)."""

    def body(state, _):
        key, k_act, k_game = jax.random.split(state.key, 3)
        obs = observe(state.games)
        state, action, info = learner.act(state.replace(key=key), obs, k_act)
        games, _, reward, stats = step_games(learner.game, learner.env_params, state.games, action, k_game,
                                             learner.arch)
        return state.replace(games=games), {"obs": obs.frames, **info, **stats, "reward": reward}

    return jax.lax.scan(body, state, None, length=length)


def _train_step(learner: Learner, state):
    return learner.train_step(state)


_donating = jax.jit(_train_step, donate_argnums=1)
_keeping = jax.jit(_train_step)


def train_program(learner: Learner, state):
    """`learner.train_step(state)`, jitted: one compiled program per learner's static half."""
    return (_donating if learner.donate_state else _keeping)(learner, state)
