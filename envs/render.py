"""Rendering of the Slither game as pure ``jnp`` functions.

Two renderers share one picture of the world:

* :func:`render_raw` draws the full RGB frame the thesis's agent saw: 500 x 300
  (width x height, array shape ``[300, 500, 3]``, ``uint8``), camera centred on the
  player's head (with ``RenderSpec.camera == "heading"`` the view also turns with the
  player, its heading up the screen).
* :func:`render_obs` draws the pre-processed observation directly: the central
  300 x 300 crop at half resolution, one channel = max over R, G, B
  (``[150, 150]`` float32 in [0, 1]).  It is the fast path used for data collection.

The picture is built so that the two agree closely (``render_obs`` ~
``preprocess(render_raw)``):

* the background is a smooth hexagonal pattern, ``bg(x, y) = b0 + b1 * s(x, y)`` per
  channel with ``s`` a sum of three plane waves whose wave vectors are integer multiples
  of ``2 pi / arena_size`` (so it tiles the torus seamlessly) and sum to zero (so it
  looks hexagonal).  Its blue channel is the brightest everywhere, so the max over RGB of
  the background is the blue channel, and the 2 x 2 mean of a plane wave is the wave
  at the block centre times a known factor; the fast path applies that factor, so on
  background the two renderers agree to float precision;
* snakes and pellets are anti-aliased discs composited with ``max`` (a disc pixel is
  ``colour * coverage`` and the frame is the per-channel maximum of background and all
  discs).  ``max`` commutes with the max over channels, so the only differences
  between the fast path and pre-processed raw frames are at disc edges (half-resolution
  coverage vs. the mean of four full-resolution coverages) and where two colours meet
  inside one 2 x 2 block (max of means vs. mean of maxes).

Cost: the background is one small matrix product per frame (separable waves); discs
are scattered as small stamps with ``.at[].max`` so the cost grows with the number of
drawn discs, not with pixels x discs.  The fast path draws only discs that can touch
the crop: the pellet cells in a fixed window around the camera and at most
``max_drawn_segments`` visible snake segments, the player's first.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
from jax import lax

from envs._xla import materialise

RAW_HEIGHT = 300
RAW_WIDTH = 500
OBS_SIZE = 150
CROP_SIZE = 300

PLAYER_COLOUR = (0.95, 0.25, 0.25)
OPPONENT_COLOURS = (
    (0.25, 0.85, 0.3),
    (1.0, 0.85, 0.2),
    (0.75, 0.35, 1.0),
    (0.2, 0.8, 0.85),
    (1.0, 0.55, 0.1),
    (0.9, 0.9, 0.9),
    (0.95, 0.4, 0.75),
    (0.55, 0.7, 1.0),
)
PELLET_COLOURS = (
    (1.0, 0.3, 0.3),
    (0.4, 1.0, 0.4),
    (0.45, 0.55, 1.0),
    (1.0, 1.0, 0.35),
    (1.0, 0.5, 1.0),
    (0.5, 1.0, 1.0),
    (0.85, 0.65, 0.35),
)
BACKGROUND_BASE = (0.07, 0.09, 0.14)
BACKGROUND_AMPLITUDE = (0.05, 0.07, 0.12)
BACKGROUND_PERIOD = 40.0
STRIPE_PERIOD = 4.0
STRIPE_DEPTH = 0.3
CAMERAS = ("north", "heading")


@dataclasses.dataclass(frozen=True)
class RenderSpec:
    """Static drawing constants (shapes and sizes, not traced).

    Attributes:
      arena_size: side of the square torus arena in raw pixels.
      cell_size: side of one pellet cell in raw pixels.
      segment_radius: radius of a snake segment disc in raw pixels.
      pellet_radius: radius of a pellet disc in raw pixels.
      max_drawn_segments: budget of visible snake segments the fast path draws;
        segments are taken in order (player head to tail, then opponent 1, ...), so
        when more are in view the tail ends of the highest-numbered opponents are
        left out of the observation (``render_raw`` draws them all).
      camera: ``"north"``: the world's axes are the screen's (the thesis's game);
        ``"heading"``: the view turns with the player, its heading pointing up the
        screen, so "a pellet left of the centre" means "turn left".
    """

    arena_size: float
    cell_size: float
    segment_radius: float = 6.0
    pellet_radius: float = 2.0
    max_drawn_segments: int = 64
    camera: str = "north"

    def __post_init__(self):
        if self.camera not in CAMERAS:
            raise ValueError(f"unknown camera {self.camera!r}; choose one of {', '.join(CAMERAS)}")

    @property
    def grid(self) -> int:
        """Number of pellet cells along one side of the arena."""
        return int(round(self.arena_size / self.cell_size))

    @property
    def wave_numbers(self) -> tuple[int, int, int]:
        """Integer wave numbers (n1, n2x, n2y) of the hexagonal background."""
        n2x = max(1, int(round(self.arena_size / BACKGROUND_PERIOD / 2)))
        n2y = max(1, int(round(n2x * math.sqrt(3.0))))
        return 2 * n2x, n2x, n2y


def disc_offsets(radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Integer pixel offsets (dy [n], dx [n]) that an anti-aliased disc can touch.

    A disc of ``radius`` pixels whose centre lies within half a pixel (per axis) of
    pixel ``c`` gives coverage ``clip(radius + 0.5 - distance, 0, 1) > 0`` only to
    pixels ``c + o`` whose square [o - 0.5, o + 0.5]^2 comes closer than
    ``radius + 0.5`` to the origin.
    """
    reach = radius + 0.5
    r = int(math.ceil(reach + 0.5))
    d = np.arange(-r, r + 1)
    dy, dx = np.meshgrid(d, d, indexing="ij")
    near_y = np.maximum(np.abs(dy) - 0.5, 0.0)
    near_x = np.maximum(np.abs(dx) - 0.5, 0.0)
    keep = near_y**2 + near_x**2 < reach**2
    return dy[keep].astype(np.int32), dx[keep].astype(np.int32)


def wrap_delta(d: jnp.ndarray, arena_size: float) -> jnp.ndarray:
    """Shortest signed difference on the torus, in [-arena_size / 2, arena_size / 2]."""
    return d - arena_size * jnp.round(d * (1.0 / arena_size))


def wrap_position(x: jnp.ndarray, arena_size: float) -> jnp.ndarray:
    """Position wrapped into the arena [0, arena_size)."""
    return x - arena_size * jnp.floor(x * (1.0 / arena_size))


def _brightness(colours) -> np.ndarray:
    """Max over R, G, B of each colour: what pre-processing keeps of it."""
    return np.max(np.asarray(colours, np.float32), axis=-1)


def _background_coefficients(spec: RenderSpec):
    """Per-channel coefficients (b0 [3], b1 [3]) with bg = b0 + b1 * s, s in [-1.5, 3]."""
    base = np.asarray(BACKGROUND_BASE, np.float32)
    amp = np.asarray(BACKGROUND_AMPLITUDE, np.float32)
    b1 = amp / 4.5
    b0 = base + 1.5 * b1
    return b0, b1


def _wave(omega: float, camera, offsets: np.ndarray):
    """``cos(omega * (camera + offsets))`` for a scalar camera coordinate and constant
    pixel offsets, by the angle-addition formula (two scalar trig calls instead of
    one per pixel)."""
    phase = omega * camera
    return jnp.cos(phase) * np.cos(omega * offsets) - jnp.sin(phase) * np.sin(omega * offsets)


def _background(cam_x, cam_y, offsets_x, offsets_y, spec: RenderSpec, b0: float, b1,
                half_res: bool):
    """One channel of the background [len(offsets_y), len(offsets_x)].

    Pixel centres lie at ``camera + offsets`` in the world; ``b0``/``b1`` are the
    channel's coefficients (``b1`` may be traced: it carries the contrast).  With ``half_res`` the waves are damped by the exact
    factor that averaging a 2 x 2 block of full-resolution samples applies.  The
    waves are separable, so this is one rank-2 matrix product (XLA evaluates it far
    faster than the equivalent broadcast expression).
    """
    n1, n2x, n2y = spec.wave_numbers
    w = 2.0 * math.pi / spec.arena_size
    w1, w2x, w2y = w * n1, w * n2x, w * n2y
    if half_res:
        f1 = math.cos(w1 / 2)
        f2 = math.cos(w2x / 2) * math.cos(w2y / 2)
    else:
        f1 = f2 = 1.0
    cam_x = wrap_position(cam_x, spec.arena_size)
    cam_y = wrap_position(cam_y, spec.arena_size)
    ones = np.ones(len(offsets_y), np.float32)
    left = jnp.stack([ones, _wave(w2y, cam_y, offsets_y)], axis=1)
    right = jnp.stack(
        [b0 + (b1 * f1) * _wave(w1, cam_x, offsets_x), (2.0 * f2 * b1) * _wave(w2x, cam_x, offsets_x)],
        axis=0,
    )
    return left @ right


def _background_turned(cam_x, cam_y, axes, offsets_x, offsets_y, spec: RenderSpec, b0: float, b1,
                       half_res: bool):
    """:func:`_background` for a view whose axes are turned: the pixel at view offsets
    (qx, qy) shows the world point ``camera + qx * axes[0] + qy * axes[1]`` (``axes``: two
    traced unit vectors, the screen's right and down in world coordinates).

    Each of the three plane waves ``cos(k . p)`` is ``cos(phi + a qx + b qy)`` in view
    coordinates, with ``a = k . axes[0]``, ``b = k . axes[1]``: a rank-2 outer product by the
    angle-addition formula, so the background is one rank-6 matrix product. With
    ``half_res`` each wave is damped by the factor a 2 x 2 block mean of full-resolution
    samples applies to it, ``cos(a / 2) cos(b / 2)``.
    """
    n1, n2x, n2y = spec.wave_numbers
    w = 2.0 * math.pi / spec.arena_size
    waves = ((w * n1, 0.0, 1.0), (w * n2x, w * n2y, 1.0), (w * n2x, -w * n2y, 1.0))
    cam_x = wrap_position(cam_x, spec.arena_size)
    cam_y = wrap_position(cam_y, spec.arena_size)
    (rx, ry), (dx, dy) = axes
    left, right = [], []
    for kx, ky, weight in waves:
        phi = kx * cam_x + ky * cam_y
        a = kx * rx + ky * ry
        b = kx * dx + ky * dy
        gain = b1 * weight * (jnp.cos(a / 2) * jnp.cos(b / 2) if half_res else 1.0)
        cols = phi + a * offsets_x
        rows = b * offsets_y
        left += [jnp.cos(rows), -jnp.sin(rows)]
        right += [gain * jnp.cos(cols), gain * jnp.sin(cols)]
    left = jnp.stack([jnp.ones(len(offsets_y), jnp.float32)] + left, axis=1)
    right = jnp.stack([jnp.full(len(offsets_x), b0, jnp.float32)] + right, axis=0)
    return left @ right


def _draw_background(spec: RenderSpec, cam_x, cam_y, axes, offsets_x, offsets_y, b0, b1, half_res: bool):
    """One channel of the background for the spec's camera (see :func:`_background`)."""
    if spec.camera == "north":
        return _background(cam_x, cam_y, offsets_x, offsets_y, spec, b0, b1, half_res)
    return _background_turned(cam_x, cam_y, axes, offsets_x, offsets_y, spec, b0, b1, half_res)


def view_axes(spec: RenderSpec, state):
    """The screen's right and down as world vectors ``((rx, ry), (dx, dy))``: the world's own
    axes for the ``north`` camera; for ``heading``, down is the player's heading reversed and
    right is the heading turned clockwise (a turn to the right)."""
    if spec.camera == "north":
        return (1.0, 0.0), (0.0, 1.0)
    c, s = jnp.cos(state.heading[0]), jnp.sin(state.heading[0])
    return (-s, c), (-c, -s)


def view_offsets(spec: RenderSpec, axes, dx, dy):
    """World deltas (dx, dy) from the camera as view offsets (right, down) in raw pixels."""
    if spec.camera == "north":
        return dx, dy
    (rx, ry), (ux, uy) = axes
    return dx * rx + dy * ry, dx * ux + dy * uy


def _window_span(spec: RenderSpec, width: float, height: float) -> tuple[float, float]:
    """The world span (x, y) a width x height view can show: the view itself, or for a
    turning camera the square around its circumscribed circle."""
    if spec.camera == "north":
        return width, height
    diameter = math.hypot(width, height)
    return diameter, diameter


def segment_shading(num_segments: int, stripe_phase: jnp.ndarray) -> jnp.ndarray:
    """Brightness factor [S, M] of each segment: a triangle-wave stripe pattern of
    ``STRIPE_PERIOD`` segments that travels with the body."""
    k = jnp.arange(num_segments, dtype=jnp.float32)
    t = (k[None, :] - stripe_phase[:, None]) * (1.0 / STRIPE_PERIOD)
    t = t - jnp.floor(t)
    return 1.0 - STRIPE_DEPTH * jnp.abs(2.0 * t - 1.0)


def snake_colours(num_snakes: int) -> np.ndarray:
    """RGB colour [S, 3] of each snake; snake 0 is the player."""
    opp = [OPPONENT_COLOURS[i % len(OPPONENT_COLOURS)] for i in range(num_snakes - 1)]
    return np.asarray([PLAYER_COLOUR] + opp, np.float32).reshape(num_snakes, 3)


def pellet_colour_index(iy, ix, dx, dy):
    """Palette index of the pellet in cell (iy, ix): a hash of its cell and position."""
    h = iy * 7 + ix * 13 + jnp.floor(dx).astype(jnp.int32) * 3 + jnp.floor(dy).astype(jnp.int32)
    return jnp.mod(h, len(PELLET_COLOURS))


def _pellet_window(spec: RenderSpec, state, camera_x, camera_y, span_x, span_y):
    """Pellets of the cells that can touch a view of span_x x span_y around the camera.

    Pellets lie at least their radius inside their cell, so only cells overlapping
    the view matter.  Returns world x [n], y [n], value [n] (0 = no pellet) and
    palette index [n].
    """
    g = spec.grid
    cs = spec.cell_size
    nx = int(math.ceil(span_x / cs)) + 1
    ny = int(math.ceil(span_y / cs)) + 1
    x0 = jnp.floor((camera_x - span_x / 2) / cs).astype(jnp.int32)
    y0 = jnp.floor((camera_y - span_y / 2) / cs).astype(jnp.int32)
    ix = jnp.mod(x0 + jnp.arange(nx), g)
    iy = jnp.mod(y0 + jnp.arange(ny), g)
    iyy = jnp.repeat(iy, nx)
    ixx = jnp.tile(ix, ny)
    value = state.pellet_value[iyy, ixx]
    dx = state.pellet_dx[iyy, ixx]
    dy = state.pellet_dy[iyy, ixx]
    return ixx * cs + dx, iyy * cs + dy, value, pellet_colour_index(iyy, ixx, dx, dy)


def _stamp(image_flat, height, width, row, col, value, radius):
    """Scatter-max anti-aliased discs into a flat image [height * width].

    ``row``/``col`` [n] are continuous pixel coordinates (pixel centres at
    integers), ``value`` [n] the full-coverage value of each disc (0 draws nothing).
    A pixel gets ``value * clip(radius + 0.5 - distance, 0, 1)``.  Work arrays are
    laid out [offsets, n] (XLA on CPU vectorises broadcasts along the leading axis
    far better than along the trailing one).
    """
    oy, ox = disc_offsets(radius)
    oy = oy.astype(np.float32)[:, None]
    ox = ox.astype(np.float32)[:, None]
    base_r = jnp.floor(row + 0.5)
    base_c = jnp.floor(col + 0.5)
    fr, fc, base_r, base_c, value = materialise(row - base_r, col - base_c, base_r, base_c, value)
    ddy = oy - fr[None, :]
    ddx = ox - fc[None, :]
    cover = jnp.clip(radius + 0.5 - jnp.sqrt(ddy * ddy + ddx * ddx), 0.0, 1.0) * value[None, :]
    py = base_r[None, :] + oy
    px = base_c[None, :] + ox
    inside = (py >= 0) & (py < height) & (px >= 0) & (px < width)
    flat = jnp.where(inside, py * width + px, height * width).astype(jnp.int32)
    return image_flat.at[flat.reshape(-1)].max(cover.reshape(-1), mode="drop")


def render_raw(spec: RenderSpec, state, active, contrast=1.0):
    """Full RGB frame [300, 500, 3] uint8 centred on the player's head.

    Args:
      spec: static drawing constants.
      state: a :class:`envs.slither.SlitherState` (segment ``x``/``y`` [S, M],
        ``stripe_phase`` [S], ``pellet_value``/``pellet_dx``/``pellet_dy`` [G, G]).
      active: [S, M] bool, which segments exist.
      contrast: scale of the background's hexagon pattern around its mean brightness
        (1: the game's own; 0: a flat background); may be traced.
    """
    h, w = RAW_HEIGHT, RAW_WIDTH
    cam_x = state.x[0, 0]
    cam_y = state.y[0, 0]
    off_x = np.arange(w, dtype=np.float32) + 0.5 - w / 2
    off_y = np.arange(h, dtype=np.float32) + 0.5 - h / 2
    b0, b1 = _background_coefficients(spec)
    axes = view_axes(spec, state)
    channels = [
        _draw_background(spec, cam_x, cam_y, axes, off_x, off_y, b0[c], b1[c] * contrast, half_res=False).reshape(-1)
        for c in range(3)
    ]

    def to_px(wx, wy):
        right, down = view_offsets(spec, axes, wrap_delta(wx - cam_x, spec.arena_size),
                                    wrap_delta(wy - cam_y, spec.arena_size))
        return down + (h / 2 - 0.5), right + (w / 2 - 0.5)

    px_, py_, pval, pcol = _pellet_window(spec, state, cam_x, cam_y, *_window_span(spec, float(w), float(h)))
    p_row, p_col = to_px(px_, py_)
    p_colours = jnp.asarray(np.asarray(PELLET_COLOURS, np.float32).T)[:, pcol]
    p_colours = jnp.where(pval[None] > 0, p_colours, 0.0)

    s, m = active.shape
    shade = segment_shading(m, state.stripe_phase)
    s_colours = jnp.asarray(snake_colours(s).T)[:, :, None] * shade[None]
    s_colours = jnp.where(active[None], s_colours, 0.0).reshape(3, s * m)
    s_row, s_col = to_px(state.x.reshape(-1), state.y.reshape(-1))
    for c in range(3):
        channels[c] = _stamp(channels[c], h, w, p_row, p_col, p_colours[c], spec.pellet_radius)
        channels[c] = _stamp(channels[c], h, w, s_row, s_col, s_colours[c], spec.segment_radius)
    image = jnp.stack([ch.reshape(h, w) for ch in channels], axis=-1)
    return jnp.round(jnp.clip(image, 0.0, 1.0) * 255.0).astype(jnp.uint8)


def _compact(mask, budget):
    """Indices [budget] of the first ``budget`` True entries of ``mask``; the rest
    point one past the end (``mask.shape[0]``)."""
    n = mask.shape[0]
    rank = lax.associative_scan(jnp.add, mask.astype(jnp.int32)) - 1
    slot = jnp.where(mask & (rank < budget), rank, budget)
    return jnp.full((budget + 1,), n, jnp.int32).at[slot].set(
        jnp.arange(n, dtype=jnp.int32), mode="drop"
    )[:budget]


def render_obs(spec: RenderSpec, state, active, contrast=1.0, size: int = OBS_SIZE):
    """Pre-processed observation [150, 150] float32 in [0, 1], drawn directly.

    Same arguments as :func:`render_raw`.  Output pixel (i, j) stands for the raw
    pixels (2i .. 2i+1, 100 + 2j .. 100 + 2j+1); its centre in the world is
    ``camera + (2j - 149, 2i - 149)``.  ``size`` (static) draws a larger or smaller
    crop the same way: ``[size, size]``, the central ``2 size`` x ``2 size`` raw pixels
    at half resolution, pixel centres at ``camera + (2j - (size - 1), 2i - (size - 1))``
    (an even ``size`` keeps the 150 x 150 observation's pixel centres).
    """
    n = int(size)
    half_crop = float(n)
    cam_x = state.x[0, 0]
    cam_y = state.y[0, 0]
    grid = 2.0 * np.arange(n, dtype=np.float32) - (half_crop - 1)
    b0, b1 = _background_coefficients(spec)
    bright = int(np.argmax(b0 + 3.0 * b1))
    axes = view_axes(spec, state)
    image = _draw_background(
        spec, cam_x, cam_y, axes, grid, grid, b0[bright], b1[bright] * contrast, half_res=True
    ).reshape(-1)

    def to_px(wx, wy):
        right, down = view_offsets(spec, axes, wrap_delta(wx - cam_x, spec.arena_size),
                                    wrap_delta(wy - cam_y, spec.arena_size))
        return (down + (half_crop - 1)) * 0.5, (right + (half_crop - 1)) * 0.5

    span = 2.0 * half_crop
    px_, py_, pval, pcol = _pellet_window(spec, state, cam_x, cam_y, *_window_span(spec, span, span))
    pb = jnp.asarray(_brightness(PELLET_COLOURS))[pcol]
    pb = jnp.where(pval > 0, pb, 0.0)
    image = _stamp(image, n, n, *to_px(px_, py_), pb, spec.pellet_radius / 2)

    s, m = active.shape
    shade = segment_shading(m, state.stripe_phase)
    seg_b = jnp.asarray(_brightness(snake_colours(s)))[:, None] * shade
    seg_b = jnp.where(active, seg_b, 0.0).reshape(-1)
    row, col = to_px(state.x.reshape(-1), state.y.reshape(-1))
    reach = (half_crop + spec.segment_radius + 1.0) * 0.5
    centre = (half_crop - 1) * 0.5
    visible = (seg_b > 0) & (jnp.abs(row - centre) < reach) & (jnp.abs(col - centre) < reach)
    chosen = _compact(visible, min(spec.max_drawn_segments, s * m))
    pad = jnp.zeros((1,), jnp.float32)
    row = jnp.concatenate([row, pad])[chosen]
    col = jnp.concatenate([col, pad])[chosen]
    seg_b = jnp.concatenate([seg_b, pad])[chosen]
    image = _stamp(image, n, n, row, col, seg_b, spec.segment_radius / 2)
    return image.reshape(n, n)
