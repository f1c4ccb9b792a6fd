"""The `turned` view (envs.turned_view): the north-up screen's pixels turned by the heading the
optical flow reads, against a NumPy rotation of the same screen, against the true heading's
camera, at the corners, beside the game it wraps; and the levels' new names with their old ones."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdrl.runs.config import RunConfig, saved_config, upgrade
from envs.flow_view import FlowView, FlowViewState, make_game
from envs.render import OBS_SIZE
from envs.slither import (LEVEL_ALIASES, LEVEL_GAMES, LEVELS, Slither, SlitherState, canonical_level, level_game,
                          level_params)
from envs.turned_view import SCREEN_SIZE, TurnedView

SIZES = {"num_opponents": 3, "max_segments": 20, "arena_size": 1000.0}
GAME_FIELDS = [f.name for f in dataclasses.fields(SlitherState)]


@pytest.fixture(scope="module")
def played():
    """(view, params, states): the turned view of a small game and its states over 16 steps of
    play, turning right for 8 steps, then ahead (the first state the reset one)."""
    view, params = TurnedView(Slither(**SIZES)), level_params("thesis")
    _, state = view.jit.reset(jax.random.PRNGKey(7), params)
    states = [state]
    for t in range(16):
        buttons = jnp.array([t < 8, 0.0, 0.0], jnp.float32)
        _, state, *_ = view.jit.step(jax.random.PRNGKey(100 + t), state, buttons, params)
        states.append(state)
    return view, params, states


def _true_heading(state: FlowViewState) -> FlowViewState:
    """The state with the view turned by the player's true heading, not the one read off the pixels."""
    h = state.heading[0]
    return state.replace(view_heading=jnp.stack([jnp.cos(h), jnp.sin(h)]))


def _rotated(screen: np.ndarray, angle: float, size: int) -> np.ndarray:
    """The central size x size of `screen` turned so that the screen direction at `angle`
    (radians, x right, y down) points up: each output pixel's centre, its offset from the centre
    rotated by angle + 90 degrees, sampled bilinearly between the four pixel centres around it;
    0 where that point lies beyond the outermost pixel centres."""
    side = screen.shape[0]
    q = np.arange(size) - (size - 1) / 2
    qy, qx = np.meshgrid(q, q, indexing="ij")
    turn = angle + np.pi / 2  # "up", (0, -1), onto (cos angle, sin angle)
    x = np.cos(turn) * qx - np.sin(turn) * qy + (side - 1) / 2
    y = np.sin(turn) * qx + np.cos(turn) * qy + (side - 1) / 2
    out = np.zeros((size, size), np.float64)
    inside = (x >= 0) & (x <= side - 1) & (y >= 0) & (y <= side - 1)
    x0 = np.clip(np.floor(x).astype(int), 0, side - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, side - 2)
    fx, fy = x - x0, y - y0
    s = screen.astype(np.float64)
    value = ((1 - fy) * (1 - fx) * s[y0, x0] + (1 - fy) * fx * s[y0, x0 + 1]
             + fy * (1 - fx) * s[y0 + 1, x0] + fy * fx * s[y0 + 1, x0 + 1])
    out[inside] = value[inside]
    return out


def test_the_view_is_the_screen_turned_by_the_heading_read(played):
    """Every pixel of the 150 x 150 view is the large north-up screen turned (bilinear) by the
    state's view heading, as a plain NumPy rotation turns it; the screen's central 150 x 150 is
    the game's own north-up observation, so the first frame (heading up) is that observation."""
    view, params, states = played
    assert SCREEN_SIZE == 212 and view.screen_size == SCREEN_SIZE
    get_obs, screen = jax.jit(view.get_obs), jax.jit(view.screen)
    angles = []
    for state in states[4::4] + [state.replace(view_heading=jnp.array([0.6, 0.8])) for state in states[-1:]]:
        shown, large = np.asarray(get_obs(state, params)), np.asarray(screen(state, params))
        assert shown.shape == (OBS_SIZE, OBS_SIZE) and large.shape == (SCREEN_SIZE, SCREEN_SIZE)
        angle = float(np.arctan2(state.view_heading[1], state.view_heading[0]))
        angles.append(angle)
        np.testing.assert_allclose(shown, _rotated(large, angle, OBS_SIZE), atol=1e-4, rtol=0)
    assert np.ptp(np.degrees(angles[:-1])) > 30  # the views turned by several headings read
    first, cut = np.asarray(get_obs(states[0], params)), (SCREEN_SIZE - OBS_SIZE) // 2
    north = np.asarray(view.game.jit.get_obs(SlitherState(**{n: getattr(states[0], n) for n in GAME_FIELDS}), params))
    np.testing.assert_allclose(np.asarray(screen(states[0], params))[cut:cut + OBS_SIZE, cut:cut + OBS_SIZE], north,
                               atol=1e-4, rtol=0)
    np.testing.assert_allclose(first, north, atol=1e-4, rtol=0)


def test_turned_by_the_true_heading_it_is_the_true_heading_cameras_view(played):
    """Turned by the player's true heading, the view is level `turned-true`'s (the renderer
    drawing the world at that heading) up to the blur of bilinear resampling, inside the disc
    both hold; turned 5 degrees off, it is several times further away."""
    view, params, states = played
    true_camera = Slither(**{**LEVEL_GAMES["turned-true"], **SIZES})
    assert level_game("turned-true").spec.camera == true_camera.spec.camera == "heading"
    get_obs = jax.jit(view.get_obs)
    q = np.arange(OBS_SIZE) - (OBS_SIZE - 1) / 2
    disc = np.hypot(*np.meshgrid(q, q)) < 70
    right, wrong = [], []
    for state in states[2::2]:
        expected = np.asarray(true_camera.jit.get_obs(SlitherState(**{n: getattr(state, n) for n in GAME_FIELDS}),
                                                      params))
        truly = _true_heading(state)
        off = float(state.heading[0]) + np.radians(5.0)
        for errors, shown in ((right, truly), (wrong, truly.replace(view_heading=jnp.array([np.cos(off), np.sin(off)],
                                                                                             jnp.float32)))):
            errors.append(float(np.abs(np.asarray(get_obs(shown, params)) - expected)[disc].mean()))
    assert max(right) < 0.005, right  # measured about 0.002
    assert min(wrong) > 3 * max(right), (right, wrong)


def test_at_45_degrees_the_large_screen_fills_the_corners(played):
    """Turned by 45 degrees, no pixel of the view is blank (the screen's background is never 0);
    turning the plain 150 x 150 observation instead blanks its corners (about 17 % of the view:
    the four triangles the turned square leaves out)."""
    view, params, states = played
    state = states[-1].replace(view_heading=jnp.array([np.sqrt(0.5), np.sqrt(0.5)], jnp.float32))
    shown = np.asarray(jax.jit(view.get_obs)(state, params))
    assert np.all(shown > 0)
    plain = TurnedView(view.game, screen_size=OBS_SIZE)
    corners = np.asarray(jax.jit(plain.get_obs)(state, params))
    blank = corners == 0
    assert blank[0, 0] and blank[0, -1] and blank[-1, 0] and blank[-1, -1] and not blank[OBS_SIZE // 2].any()
    assert 0.15 < blank.mean() < 0.19, blank.mean()
    assert np.isfinite(corners).all()
    with pytest.raises(ValueError, match="must hold the 150 x 150 view"):
        TurnedView(view.game, screen_size=100)


def test_the_wrapper_holds_no_game_state(played):
    """The wrapper steps the wrapped game: its state's game fields, rewards and ends are the
    game's own step's; only the flow frame and the view heading are its own."""
    view, params, states = played
    state, key, buttons = states[5], jax.random.PRNGKey(3), jnp.array([1.0, 0.0, 1.0])
    new, reward, term, trunc, _ = view.jit.step_state(key, state, buttons, params)
    game_state = SlitherState(**{n: getattr(state, n) for n in GAME_FIELDS})
    plain, plain_reward, plain_term, plain_trunc, _ = view.game.jit.step_state(key, game_state, buttons, params)
    for name in GAME_FIELDS:
        np.testing.assert_array_equal(np.asarray(getattr(new, name)), np.asarray(getattr(plain, name)), err_msg=name)
    assert (float(reward), bool(term), bool(trunc)) == (float(plain_reward), bool(plain_term), bool(plain_trunc))
    assert {f.name for f in dataclasses.fields(new)} - set(GAME_FIELDS) == {"flow_frame", "view_heading"}


def test_the_wrapper_stands_in_for_the_game():
    """`make_game(camera="turned")` and level `turned` give the wrapper; it equals a wrapper of an
    equal game (so jitted functions taking it compile once), not the flow view of the same game,
    and forwards what it does not hold."""
    game = Slither(**SIZES)
    view = make_game(camera="turned", **SIZES)
    assert isinstance(view, TurnedView) and view == TurnedView(game) and hash(view) == hash(TurnedView(game))
    assert view != FlowView(game) and FlowView(game) != view and view != TurnedView(game, screen_size=OBS_SIZE)
    assert view.camera == "turned" and view.arena_size == game.arena_size and view.obs_shape == (OBS_SIZE, OBS_SIZE)
    assert isinstance(level_game("turned"), TurnedView) and isinstance(level_game("turned-redrawn"), FlowView)
    assert type(level_game("turned-redrawn")) is FlowView
    with pytest.raises(ValueError, match="turns a north-up game's screen"):
        TurnedView(Slither(camera="heading", **SIZES))
    assert set(view.jit.__dataclass_fields__) == {"reset", "reset_state", "step", "step_state", "get_obs",
                                                  "render_raw", "in_view"}


def test_old_level_names_are_aliases_of_the_new():
    """The levels' old names give the new levels, in the game and in a run's config (a saved
    config.json under an old name loads under the new)."""
    assert LEVEL_ALIASES == {"heading": "turned-true-visible", "thesis-heading": "turned-true",
                             "thesis-flow": "turned-redrawn"}
    assert all(new in LEVELS and old not in LEVELS for old, new in LEVEL_ALIASES.items())
    assert level_params("thesis-flow") == level_params("turned-redrawn")
    assert level_game("thesis-heading") == level_game("turned-true")
    assert level_game("thesis-flow") == level_game("turned-redrawn") and level_game("heading") == level_game(
        "turned-true-visible")
    assert canonical_level("thesis") == "thesis" and canonical_level("thesis-flow") == "turned-redrawn"
    assert RunConfig(level="thesis-flow").level == "turned-redrawn"
    assert RunConfig(level="heading") == RunConfig(level="turned-true-visible")
    assert upgrade({"game": {"level": "thesis-heading"}}) == {"level": "turned-true"}
    saved = RunConfig(level="turned-redrawn").to_dict()
    saved["game"]["level"] = "thesis-flow"
    assert saved_config(saved) == RunConfig(level="turned-redrawn")
    with pytest.raises(ValueError, match="unknown game level 'hard'"):
        level_game("hard")
