"""The north-up game's symmetries: quarter turns and mirror images of a frame, with the buttons
they map to.

With the ``north`` camera the player's head is the centre of every frame and the arena is a
square torus, so turning the whole world by a quarter turn about the head, or mirroring it, gives
another world the game could be in (but for the grid of cells the pellets keep to), and its
frame is the original frame turned or mirrored (the observation grid is symmetric about its
centre, so pixel centres land on pixel centres).  What a button does relative to the snake's
heading does not change under a turn; under a mirror, clockwise becomes counter-clockwise, so
"turn right" and "turn left" swap.  Together the eight
transforms form the dihedral group D4, the data augmentation a north-up policy can be trained with
(a policy that steers correctly is invariant under the turns and swaps its turn buttons under the
mirror).  Two things in a frame are not symmetric: the background's hexagon pattern (six-fold,
not four-fold) and the slither wiggle of both turn buttons pressed together, whose phase a
mirror reverses; neither decides where a pellet is.

:func:`turn_to_heading` turns a north-up frame by any angle, to the player's heading: the
``heading`` camera's view of the same world (bilinear, within the disc the north-up frame holds);
:func:`heading_from_flow` reads that heading off two consecutive frames, from the pixels alone.

A transform is ``(quarter_turns, mirror)``: the frame is first mirrored left to right
(columns reversed), then turned ``quarter_turns`` times counter-clockwise as displayed
(``jnp.rot90``).  In world terms, with (dx, dy) a point's offset from the head (x right,
y down the screen): mirror maps it to (-dx, dy), one quarter turn to (dy, -dx).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jax.scipy.ndimage

RIGHT, LEFT, ACCELERATE = 0, 1, 2  # the game's button order
MIRRORED_BUTTONS = (LEFT, RIGHT, ACCELERATE)  # what each button becomes in a mirror image
TRANSFORMS = tuple((k, m) for m in (False, True) for k in range(4))  # the eight, (quarter_turns, mirror)


def transform_frame(frame: jax.Array, quarter_turns: jax.Array, mirror: jax.Array) -> jax.Array:
    """One square frame ``[..., S, S]`` mirrored left to right if ``mirror``, then turned
    ``quarter_turns`` (0-3, may be traced) times counter-clockwise."""
    if frame.shape[-1] != frame.shape[-2]:
        raise ValueError(f"frames must be square to turn a quarter: got {frame.shape[-2:]}")
    frame = jnp.where(mirror, jnp.flip(frame, axis=-1), frame)
    turns = [lambda f, k=k: jnp.rot90(f, k, axes=(-2, -1)) for k in range(4)]
    return jax.lax.switch(jnp.asarray(quarter_turns) % 4, turns, frame)


def transform_buttons(buttons: jax.Array, mirror: jax.Array) -> jax.Array:
    """Buttons (or per-button probabilities or logits) ``[..., 3]`` as they read in the
    mirror image if ``mirror``: right and left swapped."""
    return jnp.where(mirror, buttons[..., jnp.asarray(MIRRORED_BUTTONS)], buttons)


def transform_offsets(dx: jax.Array, dy: jax.Array, quarter_turns: int, mirror: bool):
    """World offsets (dx, dy) from the head after the transform: the world move that
    :func:`transform_frame` shows (``quarter_turns`` and ``mirror`` static)."""
    if mirror:
        dx = -dx
    for _ in range(quarter_turns % 4):
        dx, dy = dy, -dx
    return dx, dy


def random_transforms(key: jax.Array, n: int) -> tuple[jax.Array, jax.Array]:
    """``n`` transforms drawn uniformly from the eight: (quarter_turns ``[n]`` int32, mirror
    ``[n]`` bool)."""
    k_turn, k_mirror = jax.random.split(key)
    return jax.random.randint(k_turn, (n,), 0, 4), jax.random.bernoulli(k_mirror, 0.5, (n,))


def augment(key: jax.Array, frames: jax.Array, buttons: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Frames ``[N, S, S]`` and their buttons ``[N, 3]``, each pair under its own random
    transform (frames turned and mirrored, buttons swapped where mirrored)."""
    turns, mirror = random_transforms(key, frames.shape[0])
    return (jax.vmap(transform_frame)(frames, turns, mirror),
            jax.vmap(transform_buttons)(buttons, mirror))


def all_transforms(frame: jax.Array) -> jax.Array:
    """The eight transforms of one frame ``[S, S]`` -> ``[8, S, S]``, in the order of
    :data:`TRANSFORMS`."""
    return jnp.stack([transform_frame(frame, k, m) for k, m in TRANSFORMS])


def symmetrised_logits(logits: jax.Array) -> jax.Array:
    """Per-button logits ``[8, 3]`` of one policy on :func:`all_transforms` of a frame, mapped
    back (the mirrored ones' turn buttons swapped) and averaged: the logits of a policy that is
    exactly invariant under the game's symmetries."""
    mirror = jnp.asarray([m for _, m in TRANSFORMS])
    return jnp.mean(jax.vmap(transform_buttons)(logits, mirror), axis=0)


def turn_to_heading(frames, heading_xy, size: int | None = None, blank: bool = False):
    """North-up frames ``[N, S, S]`` turned (bilinear) so that the direction ``heading_xy``
    ``[N, 2]`` (x right, y down the screen; any length) points up: the view the ``heading``
    camera shows, but for the corners the north-up frame does not hold (filled with its
    nearest edge pixel).  The output pixel at offsets (right q_x, down q_y) from the centre
    samples the input at q_x (-s, c) + q_y (-c, -s), with (c, s) the unit heading
    (:func:`envs.render.view_axes`).

    ``size`` (static; default S): the side of the output, the central ``size`` x ``size`` of the
    turned frame (a frame larger than the view holds the view's corners at any turn).  With
    ``blank``, an output pixel whose sample lies outside the input's pixel centres (outside
    [0, S - 1] along either axis) is 0 instead of the nearest edge pixel."""
    side = frames.shape[-1]
    size = side if size is None else int(size)
    q = jnp.arange(size, dtype=jnp.float32) - (size - 1) / 2
    qy, qx = jnp.meshgrid(q, q, indexing="ij")

    def one(frame, xy):
        c, s = xy / jnp.maximum(jnp.linalg.norm(xy), 1e-6)
        rows, cols = c * qx - s * qy + (side - 1) / 2, -s * qx - c * qy + (side - 1) / 2
        turned = jax.scipy.ndimage.map_coordinates(frame, [rows, cols], order=1, mode="nearest")
        if not blank:
            return turned
        inside = (rows >= 0) & (rows <= side - 1) & (cols >= 0) & (cols <= side - 1)
        return jnp.where(inside, turned, 0.0)

    return jax.vmap(one)(frames, heading_xy)


def heading_from_flow(previous: jax.Array, frame: jax.Array, inner_radius: float = 12.0,
                      reweightings: int = 0) -> jax.Array:
    """The player's heading ``[..., 2]`` (x right, y down; not normalised) read off two
    consecutive north-up frames ``[..., S, S]`` without any learning: the camera follows the head,
    so the world seen around it moves by minus the head's step, and the global optical flow
    (Lucas-Kanade: one translation fitted to the brightness change by least squares over the
    annulus ``inner_radius`` < r < S / 2 - 2 pixels, which leaves out the player's own body near
    the centre) points against the heading.  With ``reweightings`` > 0, the fit is repeated that
    many times with every pixel weighted down by its residual (Cauchy weights 1 / (1 + (e / c)²),
    c twice the mean absolute residual): pixels the one translation does not explain, other
    snakes moving on their own, count less.  Feed it to :func:`turn_to_heading`."""
    size = frame.shape[-1]
    q = jnp.arange(size, dtype=jnp.float32) - (size - 1) / 2
    r = jnp.hypot(q[:, None], q[None, :])
    mask = ((r > inner_radius) & (r < size / 2 - 2)).astype(jnp.float32)
    mean = (previous + frame) / 2
    gy, gx = jnp.gradient(mean, axis=-2), jnp.gradient(mean, axis=-1)
    it = frame - previous

    def solve(weight):
        def total(x):
            return jnp.sum(weight * x, axis=(-2, -1))

        axx, axy, ayy = total(gx * gx), total(gx * gy), total(gy * gy)
        bx, by = -total(gx * it), -total(gy * it)
        det = axx * ayy - axy * axy + 1e-12
        return (ayy * bx - axy * by) / det, (axx * by - axy * bx) / det

    def refit(_, flow):
        u, v = flow
        error = jnp.abs(gx * u[..., None, None] + gy * v[..., None, None] + it)
        scale = 2.0 * jnp.sum(mask * error, axis=(-2, -1), keepdims=True) / jnp.sum(mask) + 1e-12
        return solve(mask / (1.0 + jnp.square(error / scale)))

    u, v = jax.lax.fori_loop(0, reweightings, refit, solve(mask))
    return -jnp.stack([u, v], axis=-1)


FLOW_SIZE = 64  # the side the flow camera reads the heading at (see `follow_heading`)
FLOW_REWEIGHTINGS = 3  # robust refits of its flow (see `heading_from_flow`)


def flow_frame(frame: jax.Array) -> jax.Array:
    """A north-up observation ``[..., S, S]`` area-resized to ``FLOW_SIZE``, what
    :func:`follow_heading` compares (at the game's 150 x 150 a step moves the world by several
    pixels, too far for one linearised flow step)."""
    return jax.image.resize(frame, frame.shape[:-2] + (FLOW_SIZE, FLOW_SIZE), method="linear", antialias=True)


def follow_heading(previous: jax.Array, frame: jax.Array, last_heading: jax.Array) -> jax.Array:
    """The unit heading ``[..., 2]`` (x right, y down) the ``flow`` camera turns its view by:
    :func:`heading_from_flow` of two consecutive north-up frames at ``FLOW_SIZE``
    (:func:`flow_frame`), the player's body, the inner quarter of the side, left out;
    ``last_heading`` where the frames show no motion; ``FLOW_REWEIGHTINGS`` robust refits.  On 2 242
    steps of 16 games of random play at level ``thesis``: median error 0.3 degrees, 90th percentile
    1.0, 99th 2.3 (one plain fit: 0.5, 3.3 and 14.1, the tail where other snakes are in view)."""
    read = heading_from_flow(previous, frame, inner_radius=FLOW_SIZE / 4, reweightings=FLOW_REWEIGHTINGS)
    norm = jnp.linalg.norm(read, axis=-1, keepdims=True)
    return jnp.where(norm > 1e-6, read / jnp.maximum(norm, 1e-6), last_heading)
