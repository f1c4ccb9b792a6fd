"""The ``flow`` view: an observation wrapper around a north-up game.

The wrapped game is the thesis's: its screen's axes are the world's. The wrapper turns the view
so that the heading shown by the optical flow between the last two north-up frames points up
the screen (:func:`envs.symmetry.follow_heading`). It reads no game state to do so: the view is
the one a pixel-only agent can make for itself. The heading it turns by is the wrapper's state,
kept beside the game's (:class:`FlowViewState`); the game itself holds none of it.

The view is drawn as the ``heading`` camera draws it, with the player's heading replaced by the
one read off the pixels.
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
from flax import struct

from envs import render as _render
from envs import symmetry
from envs.render import wrap_delta
from envs.slither import JittedSlither, Slither, SlitherParams, SlitherState


@struct.dataclass
class FlowViewState(SlitherState):
    """A game's state with the wrapper's: the game's north-up observation shrunk to
    ``envs.symmetry.FLOW_SIZE`` (``flow_frame``) and the heading the view is turned by
    (``view_heading`` [2], a unit vector, x right, y down), read off that frame and the one
    before; up the screen, ``(0, -1)``, at reset."""

    flow_frame: jnp.ndarray
    view_heading: jnp.ndarray


def _fields(state) -> dict:
    """A state's fields by name (not recursing into them, as `dataclasses.asdict` would)."""
    return {f.name: getattr(state, f.name) for f in dataclasses.fields(state)}


class FlowView:
    """The wrapper: the game's functions, with the view turned by the heading its pixels show.
    Every other attribute is the wrapped game's."""

    camera = "flow"

    def __init__(self, game: Slither):
        if game.camera != "north":
            raise ValueError(f"the flow view turns a north-up game's frames; got camera {game.camera!r}")
        self.game = game
        self.view_spec = dataclasses.replace(game.spec, camera="heading")

    def __getattr__(self, name: str):
        if name == "game":  # not set yet (a copy being made): no game to ask
            raise AttributeError(name)
        return getattr(self.game, name)

    def __repr__(self) -> str:
        return f"FlowView({self.game!r})"

    def __eq__(self, other) -> bool:
        return isinstance(other, FlowView) and self.game == other.game

    def __hash__(self) -> int:
        return hash((FlowView, self.game))

    @functools.cached_property
    def jit(self) -> JittedSlither:
        """``jax.jit`` versions of this view's functions, compiled once per view."""
        return JittedSlither(reset=jax.jit(self.reset), reset_state=jax.jit(self.reset_state),
                             step=jax.jit(self.step), step_state=jax.jit(self.step_state),
                             get_obs=jax.jit(self.get_obs), render_raw=jax.jit(self.render_raw),
                             in_view=jax.jit(self.in_view))

    def _params(self, params: SlitherParams | None) -> SlitherParams:
        return self.game.default_params if params is None else params

    def _flow_frame(self, state: SlitherState, params: SlitherParams) -> jax.Array:
        return symmetry.flow_frame(self.game.get_obs(state, params))

    def reset(self, key: jax.Array, params: SlitherParams | None = None):
        """Starts a game. Returns ``(obs, state)``."""
        params = self._params(params)
        state = self.reset_state(key, params)
        return self.get_obs(state, params), state

    def reset_state(self, key: jax.Array, params: SlitherParams | None = None) -> FlowViewState:
        params = self._params(params)
        state = self.game.reset_state(key, params)
        return FlowViewState(**_fields(state), flow_frame=self._flow_frame(state, params),
                             view_heading=jnp.asarray([0.0, -1.0], jnp.float32))

    def step(self, key: jax.Array, state: FlowViewState, action, params: SlitherParams | None = None):
        """One step of the game, and the turned view of the new state (as `Slither.step`)."""
        params = self._params(params)
        state, reward, terminated, truncated, info = self.step_state(key, state, action, params)
        return self.get_obs(state, params), state, reward, terminated, truncated, info

    def step_state(self, key: jax.Array, state: FlowViewState, action, params: SlitherParams | None = None):
        params = self._params(params)
        new, reward, terminated, truncated, info = self.game.step_state(key, state, action, params)
        frame = self._flow_frame(new, params)
        viewed = FlowViewState(**_fields(new), flow_frame=frame,
                               view_heading=symmetry.follow_heading(state.flow_frame, frame, state.view_heading))
        return viewed, reward, terminated, truncated, info

    def _as_viewed(self, state: FlowViewState) -> SlitherState:
        """What the view is drawn from: the player's heading replaced by the one read off the
        pixels (the only field of the state the drawing turns by)."""
        angle = jnp.arctan2(state.view_heading[1], state.view_heading[0])
        return state.replace(heading=state.heading.at[0].set(angle))

    def get_obs(self, state: FlowViewState, params: SlitherParams | None = None) -> jax.Array:
        """The pre-processed observation [150, 150], turned by the state's ``view_heading``."""
        params = self._params(params)
        viewed = self._as_viewed(state)
        return _render.render_obs(self.view_spec, viewed, self.game.active(viewed), params.background_contrast)

    def render_raw(self, state: SlitherState, params: SlitherParams | None = None) -> jax.Array:
        """The game's raw RGB frame, north-up: the screen the view is made from."""
        return self.game.render_raw(state, params)

    def in_view(self, state: FlowViewState) -> jax.Array:
        """[S] bool: some segment centre of snake s lies inside the turned view's crop."""
        half = _render.CROP_SIZE / 2
        viewed = self._as_viewed(state)
        arena = self.game.arena_size
        dx, dy = _render.view_offsets(self.view_spec, _render.view_axes(self.view_spec, viewed),
                                      wrap_delta(state.x - state.x[0, 0], arena),
                                      wrap_delta(state.y - state.y[0, 0], arena))
        inside = (jnp.abs(dx) < half) & (jnp.abs(dy) < half) & self.game.active(state)
        return jnp.any(inside, axis=-1)


def make_game(camera: str = "north", **sizes) -> Slither | FlowView:
    """The game of `Slither`'s static `sizes` seen by `camera`: north or heading (the game's own
    cameras), flow (this wrapper around the north-up game) or turned (`envs.turned_view`)."""
    if camera == "flow":
        return FlowView(Slither(**sizes))
    if camera == "turned":
        from envs.turned_view import TurnedView  # that module imports this one

        return TurnedView(Slither(**sizes))
    return Slither(camera=camera, **sizes)
