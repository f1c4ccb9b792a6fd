"""The ``turned`` view: an observation wrapper that turns the north-up screen's pixels.

The wrapped game is the thesis's: its screen's axes are the world's. Each observation is a
function of the screen alone: the game's north-up observation drawn over a crop large enough to
hold a 150 x 150 view at any turn (``SCREEN_SIZE``, :func:`envs.render.render_obs`), turned
(bilinear, :func:`envs.symmetry.turn_to_heading`) so that the heading the optical flow reads off
the north-up frames points up, and cut to its central 150 x 150. The heading is read as the
``flow`` view reads it (:class:`envs.flow_view.FlowView`, whose state, :class:`FlowViewState`,
this view keeps too); that view draws the world anew at the heading read, this one turns the
pixels the screen shows, so its pellets blur as a turned image's do.
"""
from __future__ import annotations

import math

import jax

from envs import render as _render
from envs import symmetry
from envs.flow_view import FlowView, FlowViewState
from envs.slither import Slither, SlitherParams

# The side of the north-up screen the view is cut from: the smallest even side (even: its pixel
# centres are the 150 x 150 observation's) whose pixel centres reach every sample of a 150 x 150
# view turned by any angle (the view's corners lie (150 - 1) / 2 * sqrt(2) pixels from its centre).
SCREEN_SIZE = 2 * math.ceil((1 + (_render.OBS_SIZE - 1) * math.sqrt(2)) / 2)


class TurnedView(FlowView):
    """The wrapper: the game's functions, each observation the north-up screen
    (``screen_size`` x ``screen_size``) turned by the heading its pixels show, its central
    150 x 150; a sample outside the screen is blank (0). Every other attribute is the wrapped
    game's."""

    camera = "turned"

    def __init__(self, game: Slither, screen_size: int = SCREEN_SIZE):
        if game.camera != "north":
            raise ValueError(f"the turned view turns a north-up game's screen; got camera {game.camera!r}")
        super().__init__(game)
        if int(screen_size) < _render.OBS_SIZE:
            raise ValueError(f"the screen must hold the {_render.OBS_SIZE} x {_render.OBS_SIZE} view; "
                             f"got screen_size {screen_size}")
        self.screen_size = int(screen_size)

    def __repr__(self) -> str:
        return f"TurnedView({self.game!r}, screen_size={self.screen_size})"

    def __eq__(self, other) -> bool:
        return (isinstance(other, TurnedView) and self.game == other.game
                and self.screen_size == other.screen_size)

    def __hash__(self) -> int:
        return hash((TurnedView, self.game, self.screen_size))

    def screen(self, state: FlowViewState, params: SlitherParams | None = None) -> jax.Array:
        """The north-up screen the view is cut from: the game's observation drawn over the
        central ``2 screen_size`` raw pixels, ``[screen_size, screen_size]``."""
        params = self._params(params)
        return _render.render_obs(self.game.spec, state, self.game.active(state), params.background_contrast,
                                  size=self.screen_size)

    def get_obs(self, state: FlowViewState, params: SlitherParams | None = None) -> jax.Array:
        """The pre-processed observation [150, 150]: the screen turned by the state's
        ``view_heading``."""
        return turn_screen(self.screen(state, params), state.view_heading)


def turn_screen(screen: jax.Array, heading_xy: jax.Array) -> jax.Array:
    """A north-up screen ``[S, S]`` turned (bilinear) so that ``heading_xy`` [2] (x right, y down)
    points up, its central 150 x 150; samples outside the screen blank (0)."""
    return symmetry.turn_to_heading(screen[None], heading_xy[None], size=_render.OBS_SIZE, blank=True)[0]
