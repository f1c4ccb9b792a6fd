"""A Slither.io-like game as pure JAX functions (gymnax style).

The world is a square torus (positions wrap around; there are no walls) of
``arena_size`` raw pixels, much larger than the 500 x 300 view; the camera follows the
player's head.  World units are raw screen pixels; ``y`` grows downwards (as image
rows do), headings are angles in radians with direction ``(cos h, sin h)``, so a
growing heading turns clockwise on screen ("right") and a shrinking heading turns
counter-clockwise ("left").

Snakes: snake 0 is the player, snakes 1 .. num_opponents are scripted opponents.  A
snake is ``max_segments`` points spaced ``segment_spacing`` apart along its path (index
0 = head) and a continuous ``length`` in segments; segment ``k`` exists while
``k < length``.  Each step the head moves ``speed`` along its heading and the body is
resampled along the path the head left behind (one gather + interpolation, no loop
over segments).  With the default speeds being whole multiples of the spacing the body
follows the head's path exactly.

Actions: 3 floats in [0, 1], index 0 = turn right, 1 = turn left, 2 = accelerate;
each is performed when its value is > 0.5.  Right+left together = slither forward: the
heading oscillates sinusoidally around its current direction (mean heading kept).
Neither = keep the heading.  Accelerate moves at ``boost_speed`` and costs
``boost_cost`` segments of length per step (only while ``length > min_boost_length``).

Pellets: the arena is divided into square cells of ``pellet_cell_size``; each cell
holds at most one pellet (value 0 = empty), so there are at most
``(arena_size / pellet_cell_size) ** 2`` pellets.  The player's head within
``eat_distance`` of a pellet eats it and the player grows by its value.  Opponents do
not eat (their length is drawn when they spawn).  Each step ``pellet_spawn_tries``
random cells regrow a pellet with probability ``pellet_regrow_prob``.

Reward: the player's change in length this step (pellets eaten minus boost cost;
negative while boosting, 0 once ``max_segments`` is reached).

Collisions: a head within ``collision_distance`` of any segment of another snake
(including its head) dies.  The player dying terminates the episode.  A dying
opponent leaves pellets of ``death_pellet_value`` under every second segment of its
body and respawns at once at a random place at least ``respawn_distance`` from the
player (several opponents dying in one step respawn at different places).  Snakes never collide with
themselves.  The episode is truncated after ``max_steps`` steps.

Opponents steer by a random-turn policy driven by the step key: each step, with
probability ``opp_switch_prob``, an opponent picks a new turn rate uniformly in
``[-opp_turn_rate, opp_turn_rate]`` and keeps it until its next switch.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs import fastrng
from envs import render as _render
from envs._xla import materialise
from envs.render import RenderSpec, wrap_delta, wrap_position


@struct.dataclass
class SlitherParams:
    """Numeric physics values of the game (all may be traced / vmapped).

    Distances are in raw pixels, angles in radians, lengths in segments, times in
    steps.

    Attributes:
      speed: player's distance per step.
      boost_speed: player's distance per step while accelerating.
      segment_spacing: distance between consecutive body points.
      turn_rate: heading change per step while turning left or right.
      slither_amplitude, slither_period: right+left makes the heading change by
        ``slither_amplitude * sin(2 pi t / slither_period)`` per step.
      boost_cost: length lost per step of acceleration.
      min_boost_length: no acceleration at or below this length.
      init_length: player's length at reset.
      pellet_value: length a regular pellet gives.
      death_pellet_value: length a pellet left by a dead opponent gives.
      pellet_init_fill: chance that a cell holds a pellet at reset.
      pellet_regrow_prob: chance that a drawn empty cell regrows a pellet.
      eat_distance: head-to-pellet distance at which the player eats.
      collision_distance: head-to-segment distance at which a head dies.
      opp_speed: opponents' distance per step.
      opp_turn_rate: largest turn per step of an opponent.
      opp_switch_prob: chance per step that an opponent picks a new turn.
      opp_min_length, opp_max_length: range of opponents' lengths at (re)spawn.
      respawn_distance: least distance of a (re)spawned opponent from the player.
      max_steps: steps after which the episode is truncated.
      background_contrast: scale of the hexagon pattern of the background around its
        mean brightness (1: the thesis-like game; 0: a flat background). Rendering only.
    """

    speed: float = 6.0
    boost_speed: float = 12.0
    segment_spacing: float = 6.0
    turn_rate: float = 0.15
    slither_amplitude: float = 0.3
    slither_period: float = 12.0
    boost_cost: float = 0.25
    min_boost_length: float = 4.0
    init_length: float = 10.0
    pellet_value: float = 0.5
    death_pellet_value: float = 1.0
    pellet_init_fill: float = 0.6
    pellet_regrow_prob: float = 0.5
    eat_distance: float = 9.0
    collision_distance: float = 9.0
    opp_speed: float = 6.0
    opp_turn_rate: float = 0.12
    opp_switch_prob: float = 0.05
    opp_min_length: float = 8.0
    opp_max_length: float = 30.0
    respawn_distance: float = 400.0
    max_steps: int = 1000
    background_contrast: float = 1.0


# Named levels of the game, as overrides of the default `SlitherParams`: how much of the
# frame a world model must predict beyond the player's own motion. Copying the last frame
# is a strong predictor where the textured background and the pellets dominate the error.
LEVELS: dict[str, dict[str, float]] = {
    # the thesis-like game: hexagon-textured background, 60 % of the pellet cells filled
    "thesis": {},
    # a flat background: the scrolling texture is gone, snakes and pellets remain
    "flat": {"background_contrast": 0.0},
    # the texture, with a tenth of the cells holding a pellet (slow regrowth keeps it so)
    "sparse": {"pellet_init_fill": 0.1, "pellet_regrow_prob": 0.05},
    # flat and sparse: mostly the snakes
    "clean": {"background_contrast": 0.0, "pellet_init_fill": 0.1, "pellet_regrow_prob": 0.05},
    # the thesis-like game with its pellets drawn larger (see LEVEL_GAMES)
    "visible": {},
    # the visible level seen by a camera that turns with the player's true heading (see LEVEL_GAMES)
    "turned-true-visible": {},
    # the thesis level itself seen by that camera, its pellets as small (see LEVEL_GAMES)
    "turned-true": {},
    # the thesis level drawn anew turned by the heading its north-up frames show (see LEVEL_GAMES)
    "turned-redrawn": {},
    # the thesis level, its north-up screen's pixels turned by that heading (see LEVEL_GAMES)
    "turned": {},
}

# Old names of levels, kept so that runs and commands written under them still work: old -> new.
LEVEL_ALIASES: dict[str, str] = {
    "heading": "turned-true-visible",
    "thesis-heading": "turned-true",
    "thesis-flow": "turned-redrawn",
}

# Static drawing options of the levels that have any (`Slither` arguments, beside the level's
# `SlitherParams` overrides above).
LEVEL_GAMES: dict[str, dict[str, float | str]] = {
    # pellets drawn as large as a snake's segment (radius 6 raw pixels, not 2): at the small
    # preset's 64 x 64 a radius-2 pellet is a sub-pixel dot that brightens one pixel by about a
    # fifth of the range; at radius 6 it is a disc of
    # about 2.5 pixels, 0.8 above the background. The physics are the thesis level's (pellets
    # are placed at least their radius + 1 from their cell's edges).
    "visible": {"pellet_radius": 6.0},
    # the visible level's pellets, and a view that turns with the player, its true heading up the
    # screen (privileged: the game's state, not the pixels, says where it points): the same world
    # and physics, but "the pellet ahead and to the left" is always the same place in the frame,
    # wherever the snake heads. Behaviour cloning of the privileged policy from 51 200 frames of
    # 64 x 64 plays +8.6 on held-out games here and +3.1 with the north-up camera
    # (docs/controller.md).
    "turned-true-visible": {"pellet_radius": 6.0, "camera": "heading"},
    # the thesis level, pellets and all, its true heading up the screen
    "turned-true": {"camera": "heading"},
    # the thesis level drawn anew by the renderer at the heading the optical flow between the
    # north-up frame and the one before shows: `turned-true`'s view at the heading read off the
    # pixels (`envs.flow_view.FlowView`)
    "turned-redrawn": {"camera": "flow"},
    # the thesis level, the north-up screen's pixels turned by that heading (bilinear; blank where
    # the screen ends): a view made from the pixels alone (`envs.turned_view.TurnedView`)
    "turned": {"camera": "turned"},
}


def canonical_level(level: str) -> str:
    """A level's name today: ``level``, or the level an old name (`LEVEL_ALIASES`) stands for."""
    return LEVEL_ALIASES.get(level, level)


def _known_level(level: str) -> str:
    level = canonical_level(level)
    if level not in LEVELS:
        raise ValueError(f"unknown game level {level!r}; choose one of {sorted(LEVELS)} "
                         f"(old names: {', '.join(f'{old} = {new}' for old, new in LEVEL_ALIASES.items())})")
    return level


def level_params(level: str, params: "SlitherParams | None" = None) -> "SlitherParams":
    """``params`` (default: the defaults) with the overrides of level ``level`` (or its old name)."""
    level = _known_level(level)
    params = SlitherParams() if params is None else params
    return canonical_params(params.replace(**LEVELS[level]))


def level_game(level: str) -> "Slither":
    """The game of level ``level`` (or its old name): :class:`Slither` with the level's static
    drawing options, seen by the level's camera (`envs.flow_view.make_game`)."""
    from envs.flow_view import make_game  # the wrapper module imports this one

    return make_game(**LEVEL_GAMES.get(_known_level(level), {}))


@struct.dataclass
class SlitherState:
    """The whole game state (coordinates as separate x / y arrays).

    Attributes:
      x, y: [S, M] float32 segment positions; snake 0 = player, segment 0 = head.
      heading: [S] float32 heading angles.
      length: [S] float32 lengths in segments (segment k exists while k < length).
      stripe_phase: [S] float32 phase of the body stripes (moves with the body).
      opp_turn: [S] float32 current turn per step of each opponent's scripted policy
        (entry 0 unused).
      pellet_value: [G, G] float32 pellet value per cell, row = y cell (0 = empty).
      pellet_dx, pellet_dy: [G, G] float32 pellet position inside its cell.
      time: int32 steps since reset.
      terminated: bool, the player has died.
    """

    x: jnp.ndarray
    y: jnp.ndarray
    heading: jnp.ndarray
    length: jnp.ndarray
    stripe_phase: jnp.ndarray
    opp_turn: jnp.ndarray
    pellet_value: jnp.ndarray
    pellet_dx: jnp.ndarray
    pellet_dy: jnp.ndarray
    time: jnp.ndarray
    terminated: jnp.ndarray


def canonical_params(params: SlitherParams | None = None) -> SlitherParams:
    """``params`` with every field a float32 / int32 numpy scalar array.

    Python numbers are weakly typed in JAX, so the same values given as Python
    numbers and as arrays compile two programs; passing parameters through this
    function everywhere lets jitted functions be shared.
    """
    params = SlitherParams() if params is None else params
    return jax.tree.map(
        lambda v: np.asarray(v, np.int32 if np.issubdtype(np.asarray(v).dtype, np.integer) else np.float32),
        params,
    )


@dataclasses.dataclass(frozen=True)
class JittedSlither:
    """Jitted entry points of one :class:`Slither` (see :attr:`Slither.jit`)."""

    reset: Callable
    reset_state: Callable
    step: Callable
    step_state: Callable
    get_obs: Callable
    render_raw: Callable
    in_view: Callable


def move_bodies(x, y, heading, speed, spacing, arena_size):
    """Moves every head ``speed`` along its heading; bodies follow the head's path.

    The old points are taken as a polyline head, p1, p2, ... whose edges count as
    ``spacing`` long; the new points lie at arc lengths 0, spacing, 2 spacing, ...
    from the new head along new head -> old head -> old body.  Speeds must be > 0.

    Args:
      x, y: [S, M] positions; heading, speed: [S]; spacing: scalar.
    Returns:
      new (x, y), each [S, M].
    """
    m = x.shape[1]
    ux, uy, sp = materialise(jnp.cos(heading), jnp.sin(heading), speed)
    ux, uy, sp = ux[:, None], uy[:, None], sp[:, None]
    arc = jnp.arange(m + 1, dtype=jnp.float32)[None, :] * spacing
    b = (arc - sp) / spacing
    idx = jnp.clip(jnp.floor(b), 0, m - 1).astype(jnp.int32)
    frac = (b - idx)[:, :m]
    on_first = arc[:, :m] <= sp

    def follow(c, u):
        head = c[:, :1] + u * sp
        first = head - u * arc[:, :m]
        (g,) = materialise(jnp.take_along_axis(c, idx, axis=1))
        c0, c1 = g[:, :m], g[:, 1:]
        rest = c0 + wrap_delta(c1 - c0, arena_size) * frac
        return wrap_position(jnp.where(on_first, first, rest), arena_size)

    return follow(x, ux), follow(y, uy)


def straight_body(head_x, head_y, heading, spacing, num_segments, arena_size):
    """Positions (x, y), each [..., M], of a straight body behind the head."""
    k = jnp.arange(num_segments, dtype=jnp.float32) * spacing
    ux, uy = materialise(jnp.cos(heading), jnp.sin(heading))
    x = head_x[..., None] - ux[..., None] * k
    y = head_y[..., None] - uy[..., None] * k
    return wrap_position(x, arena_size), wrap_position(y, arena_size)


# The game's cameras (the renderer's). The flow and turned views are observation wrappers around the
# north-up game: `envs.flow_view`, `envs.turned_view`.
CAMERAS = _render.CAMERAS


class Slither:
    """The game: static sizes here, physics in :class:`SlitherParams`.

    Args:
      num_opponents: number of scripted opponent snakes.
      max_segments: segments per snake array (the longest a snake can get).
      arena_size: side of the square torus arena in raw pixels (a multiple of
        ``pellet_cell_size``, at least 1000).
      pellet_cell_size: side of a pellet cell; one pellet at most per cell.
      pellet_spawn_tries: cells drawn per step for pellet regrowth.
      segment_radius, pellet_radius: drawing radii in raw pixels.
      max_drawn_segments: snake segments the fast observation draws at most (see
        :class:`envs.render.RenderSpec`).
      camera: ``"north"`` (the screen's axes are the world's, as in the thesis's game) or
        ``"heading"`` (the view turns with the player, its heading up the screen). The view a
        pixel-only agent can make for itself is a wrapper: :class:`envs.turned_view.TurnedView`
        (or :class:`envs.flow_view.FlowView`).
    """

    def __init__(
        self,
        num_opponents: int = 8,
        max_segments: int = 40,
        arena_size: float = 1600.0,
        pellet_cell_size: float = 50.0,
        pellet_spawn_tries: int = 2,
        segment_radius: float = 6.0,
        pellet_radius: float = 2.0,
        max_drawn_segments: int = 64,
        camera: str = "north",
    ):
        if camera not in CAMERAS:
            raise ValueError(f"unknown camera {camera!r}; choose one of {', '.join(CAMERAS)}")
        grid = arena_size / pellet_cell_size
        if abs(grid - round(grid)) > 1e-6:
            raise ValueError(
                f"arena_size ({arena_size}) must be a multiple of "
                f"pellet_cell_size ({pellet_cell_size})"
            )
        if arena_size < 2 * _render.RAW_WIDTH:
            raise ValueError(f"arena_size ({arena_size}) must be >= {2 * _render.RAW_WIDTH}")
        if pellet_cell_size < 2 * pellet_radius + 4:
            raise ValueError("pellet_cell_size must exceed 2 * pellet_radius + 4")
        self.num_opponents = int(num_opponents)
        self.num_snakes = self.num_opponents + 1
        self.max_segments = int(max_segments)
        self.arena_size = float(arena_size)
        self.pellet_cell_size = float(pellet_cell_size)
        self.pellet_spawn_tries = int(pellet_spawn_tries)
        self.spec = RenderSpec(
            arena_size=self.arena_size,
            cell_size=self.pellet_cell_size,
            segment_radius=float(segment_radius),
            pellet_radius=float(pellet_radius),
            max_drawn_segments=int(max_drawn_segments),
            camera=str(camera),
        )
        self.camera = str(camera)
        self.grid = self.spec.grid
        self.pellet_margin = float(pellet_radius) + 1.0

    def _key(self) -> tuple:
        return (type(self), self.num_opponents, self.max_segments, self.arena_size, self.pellet_cell_size,
                self.pellet_spawn_tries, self.spec)

    def __eq__(self, other) -> bool:
        """Games of the same class and static sizes are equal, so jitted functions that take a
        game as a static argument compile once for all of them."""
        return isinstance(other, Slither) and self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    @functools.cached_property
    def jit(self) -> "JittedSlither":
        """``jax.jit`` versions of this game's functions, compiled once per game."""
        return JittedSlither(
            reset=jax.jit(self.reset),
            reset_state=jax.jit(self.reset_state),
            step=jax.jit(self.step),
            step_state=jax.jit(self.step_state),
            get_obs=jax.jit(self.get_obs),
            render_raw=jax.jit(self.render_raw),
            in_view=jax.jit(self.in_view),
        )

    def __repr__(self) -> str:
        return (
            f"Slither(num_opponents={self.num_opponents}, max_segments={self.max_segments}, "
            f"arena_size={self.arena_size}, pellet_cell_size={self.pellet_cell_size}, camera={self.camera!r})"
        )

    @property
    def default_params(self) -> SlitherParams:
        """Default physics values (as float32 / int32 arrays, see :func:`canonical_params`)."""
        return canonical_params(SlitherParams())

    @property
    def obs_shape(self) -> tuple[int, int]:
        """Shape of the observation returned by reset / step."""
        return (_render.OBS_SIZE, _render.OBS_SIZE)

    @property
    def num_actions(self) -> int:
        """Number of action values (right, left, accelerate)."""
        return 3

    def _spawn(self, u, head_x, head_y, params):
        """Bodies for every snake slot from 4 uniforms ``u``: heads at least
        ``respawn_distance`` from the player's head (x, y), random headings and
        lengths.  Slots get different places through fixed irrational shifts of ``u``.

        Returns (x [S, M], y [S, M], heading [S], length [S]).
        """
        shift = jnp.arange(self.num_snakes, dtype=jnp.float32)[:, None] * jnp.asarray(
            [0.6180340, 0.7548777, 0.5698403, 0.4142136], jnp.float32
        )[None, :]
        v = u[None, :] + shift
        v = v - jnp.floor(v)
        angle = v[:, 0] * (2 * math.pi)
        far = self.arena_size / 2.0
        near = jnp.minimum(params.respawn_distance, far)
        radius = near + v[:, 1] * (far - near)
        cos_a, sin_a = materialise(jnp.cos(angle), jnp.sin(angle))
        hx = head_x + radius * cos_a
        hy = head_y + radius * sin_a
        heading = v[:, 2] * (2 * math.pi)
        length = params.opp_min_length + v[:, 3] * (params.opp_max_length - params.opp_min_length)
        bx, by = straight_body(hx, hy, heading, params.segment_spacing, self.max_segments, self.arena_size)
        return bx, by, heading, jnp.clip(length, 1.0, self.max_segments)

    def _offset(self, u):
        """Pellet position inside a cell from uniforms in [0, 1)."""
        return self.pellet_margin + u * (self.pellet_cell_size - 2 * self.pellet_margin)

    def reset(self, key: jax.Array, params: SlitherParams | None = None):
        """Starts a game.  Returns ``(obs, state)``; obs is [150, 150] float32."""
        params = self.default_params if params is None else params
        state = self.reset_state(key, params)
        return self.get_obs(state, params), state

    def reset_state(self, key: jax.Array, params: SlitherParams | None = None) -> SlitherState:
        """The state :meth:`reset` starts from, without rendering it."""
        params = self.default_params if params is None else params
        g = self.grid
        u_all = fastrng.uniform(key, 7 + 3 * g * g)
        u = u_all[:7]
        ug = u_all[7:].reshape(3, g, g)
        head_x = u[0] * self.arena_size
        head_y = u[1] * self.arena_size
        heading = u[2] * (2 * math.pi)
        px, py = straight_body(head_x, head_y, heading, params.segment_spacing, self.max_segments, self.arena_size)
        ox, oy, o_heading, o_len = self._spawn(u[3:], head_x, head_y, params)
        filled = ug[0] < params.pellet_init_fill
        init_len = jnp.clip(jnp.asarray(params.init_length, jnp.float32), 1.0, self.max_segments)
        state = SlitherState(
            x=jnp.concatenate([px[None], ox[1:]], axis=0),
            y=jnp.concatenate([py[None], oy[1:]], axis=0),
            heading=jnp.concatenate([heading[None], o_heading[1:]]),
            length=jnp.concatenate([init_len[None], o_len[1:]]),
            stripe_phase=jnp.zeros((self.num_snakes,), jnp.float32),
            opp_turn=jnp.zeros((self.num_snakes,), jnp.float32),
            pellet_value=jnp.where(filled, params.pellet_value, 0.0).astype(jnp.float32),
            pellet_dx=jnp.where(filled, self._offset(ug[1]), 0.0),
            pellet_dy=jnp.where(filled, self._offset(ug[2]), 0.0),
            time=jnp.zeros((), jnp.int32),
            terminated=jnp.zeros((), bool),
        )
        return state

    def active(self, state: SlitherState) -> jnp.ndarray:
        """[S, M] bool: which segments exist."""
        return self._active(state.length)

    def _active(self, length):
        k = jnp.arange(self.max_segments, dtype=jnp.float32)
        return k[None, :] < length[:, None]

    def _eat(self, head_x, head_y, pv, pdx, pdy, params):
        """Pellets the player's head eats (searched in the 3 x 3 cells around it).

        Returns (growth, pellet_value, pellet_dx, pellet_dy) after eating; an eaten
        cell gets value and offsets 0.
        """
        g = self.grid
        cs = self.pellet_cell_size
        cx = jnp.floor(head_x / cs).astype(jnp.int32)
        cy = jnp.floor(head_y / cs).astype(jnp.int32)
        ix = jnp.mod(cx + jnp.array([-1, 0, 1, -1, 0, 1, -1, 0, 1], jnp.int32), g)
        iy = jnp.mod(cy + jnp.array([-1, -1, -1, 0, 0, 0, 1, 1, 1], jnp.int32), g)
        value = pv[iy, ix]
        ddx = wrap_delta(ix * cs + pdx[iy, ix] - head_x, self.arena_size)
        ddy = wrap_delta(iy * cs + pdy[iy, ix] - head_y, self.arena_size)
        eaten = (value > 0) & (ddx * ddx + ddy * ddy < params.eat_distance**2)
        growth = jnp.sum(jnp.where(eaten, value, 0.0))
        keep = jnp.where(eaten, 0.0, jnp.inf)
        return growth, pv.at[iy, ix].min(keep), pdx.at[iy, ix].min(keep), pdy.at[iy, ix].min(keep)

    def _collisions(self, x, y, active, params):
        """[S] bool: the head of snake s is within collision_distance of another snake."""
        s = x.shape[0]
        dx = jnp.abs(x[None, :, :] - x[:, None, :1])
        dy = jnp.abs(y[None, :, :] - y[:, None, :1])
        dx = jnp.minimum(dx, self.arena_size - dx)
        dy = jnp.minimum(dy, self.arena_size - dy)
        close = dx * dx + dy * dy < params.collision_distance**2
        other = ~jnp.eye(s, dtype=bool)[:, :, None]
        return jnp.any(close & other & active[None], axis=(1, 2))

    def _drop_pellets(self, pv, pdx, pdy, x, y, active, died, params):
        """Leaves a pellet in the cell under every second segment of dying snakes."""
        g = self.grid
        cs = self.pellet_cell_size
        x, y = x[:, ::2], y[:, ::2]
        drop = died[:, None] & active[:, ::2]
        cx = jnp.floor(x / cs)
        cy = jnp.floor(y / cs)
        ix = jnp.mod(cx.astype(jnp.int32), g)
        iy = jnp.mod(cy.astype(jnp.int32), g)
        lo, hi = self.pellet_margin, cs - self.pellet_margin
        inner_x = jnp.clip(x - cx * cs, lo, hi)
        inner_y = jnp.clip(y - cy * cs, lo, hi)
        pv = pv.at[iy, ix].max(jnp.where(drop, params.death_pellet_value, 0.0))
        pdx = pdx.at[iy, ix].max(jnp.where(drop, inner_x, 0.0))
        pdy = pdy.at[iy, ix].max(jnp.where(drop, inner_y, 0.0))
        return pv, pdx, pdy

    def _regrow(self, u, pv, pdx, pdy, params):
        """Regrowth from uniforms u [5, tries]: cell x, cell y, chance, offset x, y."""
        g = self.grid
        ix = jnp.minimum((u[0] * g).astype(jnp.int32), g - 1)
        iy = jnp.minimum((u[1] * g).astype(jnp.int32), g - 1)
        grow = (u[2] < params.pellet_regrow_prob) & (pv[iy, ix] <= 0)
        pv = pv.at[iy, ix].max(jnp.where(grow, params.pellet_value, 0.0))
        pdx = pdx.at[iy, ix].max(jnp.where(grow, self._offset(u[3]), 0.0))
        pdy = pdy.at[iy, ix].max(jnp.where(grow, self._offset(u[4]), 0.0))
        return pv, pdx, pdy

    def step(self, key: jax.Array, state: SlitherState, action, params: SlitherParams | None = None):
        """Advances one step and renders the new observation.

        Args:
          key: PRNG key for the opponents, respawns and pellet regrowth.
          state: current state.
          action: [3] floats in [0, 1] (right, left, accelerate), > 0.5 = pressed.
          params: physics values.
        Returns:
          ``(obs, state, reward, terminated, truncated, info)`` with obs [150, 150]
          float32, reward the player's change in length, info a dict with the
          player's ``length`` and the number of opponents that died this step.
        """
        params = self.default_params if params is None else params
        state, reward, terminated, truncated, info = self.step_state(key, state, action, params)
        return self.get_obs(state, params), state, reward, terminated, truncated, info

    def step_state(self, key: jax.Array, state: SlitherState, action, params: SlitherParams | None = None):
        """:meth:`step` without rendering: ``(state, reward, terminated, truncated, info)``."""
        params = self.default_params if params is None else params
        n = self.num_snakes
        tries = self.pellet_spawn_tries
        u = fastrng.uniform(key, n + 4 + 5 * tries)
        u_switch = u[:n]
        u_spawn = u[n:n + 4]
        u_regrow = u[n + 4:].reshape(5, tries)

        pressed = jnp.asarray(action) > 0.5
        right, left, boost = pressed[0], pressed[1], pressed[2]
        phase = (2.0 * math.pi) * state.time.astype(jnp.float32) / params.slither_period
        turn = jnp.where(
            right & left,
            params.slither_amplitude * jnp.sin(phase),
            (right.astype(jnp.float32) - left.astype(jnp.float32)) * params.turn_rate,
        )
        is_player = jnp.arange(n) == 0
        switch = u_switch < params.opp_switch_prob
        reuse = u_switch / jnp.maximum(params.opp_switch_prob, 1e-9)
        new_turn = (2.0 * reuse - 1.0) * params.opp_turn_rate
        opp_turn = jnp.where(switch, new_turn, state.opp_turn)
        opp_turn = jnp.where(is_player, 0.0, opp_turn)
        heading = state.heading + jnp.where(is_player, turn, opp_turn)
        heading = heading - (2 * math.pi) * jnp.floor(heading / (2 * math.pi))

        boosting = boost & (state.length[0] > params.min_boost_length)
        player_speed = jnp.where(boosting, params.boost_speed, params.speed)
        speed = jnp.where(is_player, player_speed, params.opp_speed).astype(jnp.float32)
        x, y = materialise(
            *move_bodies(state.x, state.y, heading, speed, params.segment_spacing, self.arena_size)
        )
        stripe = state.stripe_phase + speed / params.segment_spacing
        stripe = stripe - _render.STRIPE_PERIOD * jnp.floor(stripe / _render.STRIPE_PERIOD)

        growth, pv, pdx, pdy = self._eat(
            x[0, 0], y[0, 0], state.pellet_value, state.pellet_dx, state.pellet_dy, params
        )
        change = jnp.where(is_player, growth - jnp.where(boosting, params.boost_cost, 0.0), 0.0)
        length = jnp.clip(state.length + change, 1.0, self.max_segments)
        active = self._active(length)

        (hit,) = materialise(self._collisions(x, y, active, params))
        died = hit & ~is_player
        pv, pdx, pdy = self._drop_pellets(pv, pdx, pdy, x, y, active, died, params)
        bx, by, b_heading, b_len = self._spawn(u_spawn, x[0, 0], y[0, 0], params)
        x = jnp.where(died[:, None], bx, x)
        y = jnp.where(died[:, None], by, y)
        heading = jnp.where(died, b_heading, heading)
        length = jnp.where(died, b_len, length)
        stripe = jnp.where(died, 0.0, stripe)
        opp_turn = jnp.where(died, 0.0, opp_turn)
        pv, pdx, pdy = self._regrow(u_regrow, pv, pdx, pdy, params)

        time = state.time + 1
        terminated = state.terminated | hit[0]
        new_state = SlitherState(
            x=x,
            y=y,
            heading=heading,
            length=length,
            stripe_phase=stripe,
            opp_turn=opp_turn,
            pellet_value=pv,
            pellet_dx=pdx,
            pellet_dy=pdy,
            time=time,
            terminated=terminated,
        )
        reward = length[0] - state.length[0]
        truncated = (time >= params.max_steps) & ~terminated
        info = {"length": length[0], "opponents_died": jnp.sum(died)}
        return new_state, reward, terminated, truncated, info

    def get_obs(self, state: SlitherState, params: SlitherParams | None = None) -> jnp.ndarray:
        """The pre-processed observation [150, 150] float32 in [0, 1] (fast path)."""
        params = self.default_params if params is None else params
        return _render.render_obs(self.spec, state, self.active(state), params.background_contrast)

    def render_raw(self, state: SlitherState, params: SlitherParams | None = None) -> jnp.ndarray:
        """The raw RGB frame [300, 500, 3] uint8 (width 500 x height 300)."""
        params = self.default_params if params is None else params
        return _render.render_raw(self.spec, state, self.active(state), params.background_contrast)

    def in_view(self, state: SlitherState) -> jnp.ndarray:
        """[S] bool: some segment centre of snake s lies inside the observed crop."""
        half = _render.CROP_SIZE / 2
        dx, dy = _render.view_offsets(self.spec, _render.view_axes(self.spec, state),
                                      wrap_delta(state.x - state.x[0, 0], self.arena_size),
                                      wrap_delta(state.y - state.y[0, 0], self.arena_size))
        inside = (jnp.abs(dx) < half) & (jnp.abs(dy) < half) & self.active(state)
        return jnp.any(inside, axis=-1)
