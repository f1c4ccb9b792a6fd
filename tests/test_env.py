"""Tests of the Slither game, its rendering, pre-processing, policies and gym API."""

from __future__ import annotations

import math

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import envs
from envs import fastrng
from envs.policies import (BEHAVIOURS, HOLD_SWITCH_PROB, behaviour_init, behaviour_step, held_uniform_init,
                           held_uniform_step, uniform_init, uniform_step)
from envs.preprocess import central_crop, preprocess
from envs.render import wrap_delta
from envs.gym_env import game_for
from envs.slither import Slither, SlitherParams, move_bodies

GAME = game_for()
PARAMS = GAME.default_params
RIGHT = jnp.array([1.0, 0.0, 0.0])
LEFT = jnp.array([0.0, 1.0, 0.0])
SLITHER = jnp.array([1.0, 1.0, 0.0])
STRAIGHT = jnp.array([0.0, 0.0, 0.0])
BOOST = jnp.array([0.0, 0.0, 1.0])

reset = GAME.jit.reset
step = GAME.jit.step
render_raw = GAME.jit.render_raw
in_view = GAME.jit.in_view


def reset_state(key, params):
    return reset(key, params)[1]


def step_state(key, state, action, params):
    return step(key, state, action, params)[1:]


def get_obs(state):
    return GAME.jit.get_obs(state)


def quiet(state, far=True):
    """The state with every opponent parked far from the player, not turning."""
    s = state
    if far:
        hx, hy = s.x[0, 0], s.y[0, 0]
        half = GAME.arena_size / 2
        offs = jnp.arange(1, GAME.num_snakes, dtype=jnp.float32) * 40.0
        ox = hx + half + jnp.zeros_like(offs)
        oy = hy + half + offs
        k = jnp.arange(GAME.max_segments, dtype=jnp.float32) * PARAMS.segment_spacing
        s = s.replace(
            x=s.x.at[1:].set((ox[:, None] - k[None, :]) % GAME.arena_size),
            y=s.y.at[1:].set(jnp.broadcast_to(oy[:, None] % GAME.arena_size, (len(offs), GAME.max_segments))),
            heading=s.heading.at[1:].set(0.0),
        )
    return s.replace(opp_turn=jnp.zeros_like(s.opp_turn))


NO_SWITCH = PARAMS.replace(opp_switch_prob=np.float32(0.0), pellet_regrow_prob=np.float32(0.0))


def run(state, actions, params=NO_SWITCH, seed=0):
    """Steps the game through ``actions``; returns the states and rewards."""
    states, rewards, dones = [state], [], []
    for t, a in enumerate(actions):
        state, r, term, trunc, _ = step_state(jax.random.PRNGKey(seed * 1000 + t), state, a, params)
        states.append(state)
        rewards.append(float(r))
        dones.append(bool(term))
    return states, rewards, dones


def empty_pellets(state):
    return state.replace(pellet_value=jnp.zeros_like(state.pellet_value))


def test_same_key_same_episode_different_key_differs():
    def episode(seed):
        key = jax.random.PRNGKey(seed)
        obs, state = reset(key, PARAMS)
        frames, rewards = [np.asarray(obs)], []
        for t in range(12):
            obs, state, r, *_ = step(jax.random.fold_in(key, t), state, RIGHT if t % 2 else SLITHER, PARAMS)
            frames.append(np.asarray(obs))
            rewards.append(float(r))
        return np.stack(frames), np.asarray(rewards), np.asarray(state.x)

    f1, r1, x1 = episode(3)
    f2, r2, x2 = episode(3)
    f3, _, x3 = episode(4)
    np.testing.assert_array_equal(f1, f2)
    np.testing.assert_array_equal(r1, r2)
    np.testing.assert_array_equal(x1, x2)
    assert np.abs(f1 - f3).mean() > 0.01
    assert not np.allclose(x1, x3)


def test_straight_motion_keeps_heading_and_moves_at_speed():
    s0 = quiet(empty_pellets(reset_state(jax.random.PRNGKey(1), PARAMS)))
    states, rewards, dones = run(s0, [STRAIGHT] * 10)
    h0 = float(s0.heading[0])
    assert all(abs(float(s.heading[0]) - h0) < 1e-5 for s in states)
    dx = float(wrap_delta(states[-1].x[0, 0] - s0.x[0, 0], GAME.arena_size))
    dy = float(wrap_delta(states[-1].y[0, 0] - s0.y[0, 0], GAME.arena_size))
    assert dx == pytest.approx(10 * PARAMS.speed * math.cos(h0), abs=1e-2)
    assert dy == pytest.approx(10 * PARAMS.speed * math.sin(h0), abs=1e-2)
    assert rewards == [0.0] * 10 and not any(dones)
    seg = jnp.hypot(
        wrap_delta(jnp.diff(states[-1].x[0]), GAME.arena_size),
        wrap_delta(jnp.diff(states[-1].y[0]), GAME.arena_size),
    )
    np.testing.assert_allclose(np.asarray(seg), PARAMS.segment_spacing, atol=1e-3)


def turn_of(action, steps=5):
    s0 = quiet(empty_pellets(reset_state(jax.random.PRNGKey(2), PARAMS)))
    states, _, _ = run(s0, [action] * steps)
    d = float(states[-1].heading[0] - s0.heading[0])
    return (d + math.pi) % (2 * math.pi) - math.pi


def test_left_turns_left_right_turns_right():
    # y grows downwards, so "left" (counter-clockwise on screen) lowers the heading.
    assert turn_of(LEFT) == pytest.approx(-5 * PARAMS.turn_rate, abs=1e-4)
    assert turn_of(RIGHT) == pytest.approx(5 * PARAMS.turn_rate, abs=1e-4)


def test_slither_wiggles_but_keeps_mean_heading():
    period = int(PARAMS.slither_period)
    s0 = quiet(empty_pellets(reset_state(jax.random.PRNGKey(5), PARAMS)))
    states, _, _ = run(s0, [SLITHER] * period)
    swings = [abs(float(s.heading[0] - s0.heading[0])) for s in states]
    assert max(swings) > 0.5
    assert turn_of(SLITHER, steps=period) == pytest.approx(0.0, abs=1e-4)


def test_accelerate_moves_faster_and_shrinks():
    s0 = quiet(empty_pellets(reset_state(jax.random.PRNGKey(4), PARAMS)))
    states, rewards, _ = run(s0, [BOOST] * 4)
    moved = float(jnp.hypot(
        wrap_delta(states[1].x[0, 0] - s0.x[0, 0], GAME.arena_size),
        wrap_delta(states[1].y[0, 0] - s0.y[0, 0], GAME.arena_size),
    ))
    assert moved == pytest.approx(PARAMS.boost_speed, abs=1e-3)
    assert float(states[-1].length[0]) == pytest.approx(PARAMS.init_length - 4 * PARAMS.boost_cost)
    assert rewards == pytest.approx([-PARAMS.boost_cost] * 4)
    short = s0.replace(length=s0.length.at[0].set(PARAMS.min_boost_length))
    states, rewards, _ = run(short, [BOOST] * 2)
    assert rewards == [0.0, 0.0]


def test_eating_a_pellet_grows_and_rewards():
    s0 = quiet(empty_pellets(reset_state(jax.random.PRNGKey(6), PARAMS)))
    h = float(s0.heading[0])
    px = (float(s0.x[0, 0]) + PARAMS.speed * math.cos(h)) % GAME.arena_size
    py = (float(s0.y[0, 0]) + PARAMS.speed * math.sin(h)) % GAME.arena_size
    cs = GAME.pellet_cell_size
    ix, iy = int(px // cs), int(py // cs)
    s0 = s0.replace(
        pellet_value=s0.pellet_value.at[iy, ix].set(PARAMS.pellet_value),
        pellet_dx=s0.pellet_dx.at[iy, ix].set(px - ix * cs),
        pellet_dy=s0.pellet_dy.at[iy, ix].set(py - iy * cs),
    )
    states, rewards, _ = run(s0, [STRAIGHT])
    assert rewards[0] == pytest.approx(PARAMS.pellet_value)
    assert float(states[1].length[0]) == pytest.approx(PARAMS.init_length + PARAMS.pellet_value)
    assert float(states[1].pellet_value[iy, ix]) == 0.0
    assert float(states[1].pellet_value.sum()) == 0.0


def wall_ahead(state, distance):
    """Opponent 1 laid across the player's path ``distance`` ahead of its head."""
    h = float(state.heading[0])
    cx = float(state.x[0, 0]) + distance * math.cos(h)
    cy = float(state.y[0, 0]) + distance * math.sin(h)
    k = (jnp.arange(GAME.max_segments, dtype=jnp.float32) - GAME.max_segments / 2) * 4.0
    return state.replace(
        x=state.x.at[1].set((cx - math.sin(h) * k) % GAME.arena_size),
        y=state.y.at[1].set((cy + math.cos(h) * k) % GAME.arena_size),
        heading=state.heading.at[1].set(h + math.pi / 2),
        length=state.length.at[1].set(float(GAME.max_segments)),
    )


def test_head_hitting_a_body_terminates():
    s0 = quiet(empty_pellets(reset_state(jax.random.PRNGKey(7), PARAMS)))
    _, _, dones = run(wall_ahead(s0, PARAMS.speed), [STRAIGHT])
    assert dones == [True]
    _, _, dones = run(wall_ahead(s0, 200.0), [STRAIGHT] * 3)
    assert dones == [False, False, False]


def test_opponent_hitting_player_dies_respawns_and_leaves_pellets():
    s0 = quiet(empty_pellets(reset_state(jax.random.PRNGKey(8), PARAMS)))
    h = float(s0.heading[0])
    side = h + math.pi / 2
    bx, by = float(s0.x[0, 3]), float(s0.y[0, 3])
    start_x = bx + 30.0 * math.cos(side)
    start_y = by + 30.0 * math.sin(side)
    k = jnp.arange(GAME.max_segments, dtype=jnp.float32) * PARAMS.segment_spacing
    head_on = s0.replace(
        x=s0.x.at[1].set((start_x + math.cos(side) * k) % GAME.arena_size),
        y=s0.y.at[1].set((start_y + math.sin(side) * k) % GAME.arena_size),
        heading=s0.heading.at[1].set(side + math.pi),
        length=s0.length.at[1].set(12.0),
    )
    states, _, dones = run(head_on, [STRAIGHT] * 6)
    assert not any(dones)
    far = [float(jnp.hypot(wrap_delta(s.x[1, 0] - s.x[0, 0], GAME.arena_size),
                           wrap_delta(s.y[1, 0] - s.y[0, 0], GAME.arena_size))) for s in states]
    assert min(far) < 60.0 and far[-1] >= PARAMS.respawn_distance - 1.0
    assert float(states[-1].pellet_value.sum()) >= 3 * PARAMS.death_pellet_value


def test_check_env_and_spaces():
    env = gym.make("cdrl/Slither-v0", render_mode="rgb_array")
    check_env(env.unwrapped)
    assert env.observation_space == gym.spaces.Box(0.0, 1.0, (150, 150, 1), np.float32)
    assert env.action_space == gym.spaces.Box(0.0, 1.0, (3,), np.float32)
    obs, _ = env.reset(seed=11)
    frame = env.render()
    assert obs.shape == (150, 150, 1) and obs.dtype == np.float32
    assert frame.shape == (300, 500, 3) and frame.dtype == np.uint8
    np.testing.assert_allclose(obs[..., 0], preprocess(frame), atol=0.25)
    obs2, _ = gym.make("cdrl/Slither-v0").reset(seed=11)
    np.testing.assert_array_equal(obs, obs2)


def test_vmap_over_keys_and_params_matches_single_games():
    keys = jax.random.split(jax.random.PRNGKey(21), 3)
    actions = jnp.stack([RIGHT, LEFT, BOOST])
    params = jax.tree.map(lambda *v: jnp.stack(v), PARAMS, PARAMS.replace(speed=np.float32(3.0)),
                          PARAMS.replace(boost_speed=np.float32(20.0)))
    _, states = jax.jit(jax.vmap(GAME.reset))(keys, params)
    obs_b, states_b, r_b, *_ = jax.jit(jax.vmap(GAME.step))(keys, states, actions, params)
    for i in range(3):
        p_i = jax.tree.map(lambda a: a[i], params)
        _, state = reset(keys[i], p_i)
        obs_s, state_s, r_s, *_ = step(keys[i], state, actions[i], p_i)
        np.testing.assert_allclose(np.asarray(obs_b[i]), np.asarray(obs_s), atol=1e-6)
        np.testing.assert_allclose(np.asarray(states_b.x[i]), np.asarray(state_s.x), atol=1e-4)
        assert float(r_b[i]) == pytest.approx(float(r_s))
    moved = np.hypot(np.asarray(wrap_delta(states_b.x[:, 0, 0] - states.x[:, 0, 0], GAME.arena_size)),
                     np.asarray(wrap_delta(states_b.y[:, 0, 0] - states.y[:, 0, 0], GAME.arena_size)))
    np.testing.assert_allclose(moved, [6.0, 3.0, 20.0], atol=1e-3)


def test_most_pixels_change_between_consecutive_observations():
    s = reset_state(jax.random.PRNGKey(9), PARAMS)
    prev = np.asarray(get_obs(s))
    prev_raw = np.asarray(render_raw(s))
    for t in range(3):
        s, *_ = step_state(jax.random.PRNGKey(t), s, STRAIGHT, PARAMS)
        obs = np.asarray(get_obs(s))
        raw = np.asarray(render_raw(s))
        assert (np.abs(obs - prev) > 1.0 / 255).mean() > 0.5
        assert (np.abs(raw.astype(int) - prev_raw).max(axis=-1) > 0).mean() > 0.5
        prev, prev_raw = obs, raw


def test_opponent_leaves_and_reenters_the_view():
    s0 = quiet(empty_pellets(reset_state(jax.random.PRNGKey(10), PARAMS)))
    h = float(s0.heading[0])
    k = jnp.arange(GAME.max_segments, dtype=jnp.float32) * PARAMS.segment_spacing
    ax = float(s0.x[0, 0]) + 100 * math.cos(h) + 60 * math.cos(h + math.pi / 2)
    ay = float(s0.y[0, 0]) + 100 * math.sin(h) + 60 * math.sin(h + math.pi / 2)
    s0 = s0.replace(
        x=s0.x.at[1].set((ax + math.cos(h) * k) % GAME.arena_size),
        y=s0.y.at[1].set((ay + math.sin(h) * k) % GAME.arena_size),
        heading=s0.heading.at[1].set(h + math.pi),
        length=s0.length.at[1].set(10.0),
    )
    steps = int(GAME.arena_size / (PARAMS.speed + PARAMS.opp_speed)) + 10
    seen, s = [], s0
    for t in range(steps):
        seen.append(bool(in_view(s)[1]))
        s = step_state(jax.random.PRNGKey(t), s, STRAIGHT, NO_SWITCH)[0]
    seen = np.asarray(seen)
    assert seen[0]
    left = np.argmin(seen)
    assert left > 0 and not seen[left]
    assert seen[left:].any()
    back = left + int(np.argmax(seen[left:]))
    moved_away = s0.replace(x=s0.x.at[1].add(GAME.arena_size / 2))
    assert np.abs(np.asarray(get_obs(s0)) - np.asarray(get_obs(moved_away))).max() > 0.3
    assert back - left > 10


def test_fast_observation_matches_preprocessed_raw_frame():
    # Tolerance: the raw frame is quantised to uint8 (<= 0.002), the fast path uses
    # half-resolution disc coverage instead of the mean of four full-resolution
    # coverages, and max-of-means differs from mean-of-maxes where two colours meet
    # inside one 2 x 2 block; all of this happens only on disc edges.
    for seed in range(2):
        s = reset_state(jax.random.PRNGKey(30 + seed), PARAMS)
        s = s.replace(x=s.x.at[1].set(s.x[0] + 50.0), y=s.y.at[1].set(s.y[0] + 30.0))
        for t in range(5):
            s, *_ = step_state(jax.random.PRNGKey(t), s, SLITHER, PARAMS)
        assert bool(in_view(s)[1])
        diff = np.abs(np.asarray(get_obs(s)) - preprocess(np.asarray(render_raw(s))))
        assert diff.mean() < 0.005
        assert (diff > 0.05).mean() < 0.02
        assert diff.max() < 0.25


def _turned_player(state, heading: float):
    """The state with the player's body turned about its head so that it heads `heading`."""
    hx, hy = state.x[0, 0], state.y[0, 0]
    turn = heading - state.heading[0]
    c, s = jnp.cos(turn), jnp.sin(turn)
    dx, dy = wrap_delta(state.x[0] - hx, GAME.arena_size), wrap_delta(state.y[0] - hy, GAME.arena_size)
    return state.replace(x=state.x.at[0].set((hx + c * dx - s * dy) % GAME.arena_size),
                         y=state.y.at[0].set((hy + s * dx + c * dy) % GAME.arena_size),
                         heading=state.heading.at[0].set(heading))


@pytest.fixture(scope="module")
def turning_state():
    """A state after 30 steps of turning left (a curved body), an opponent beside the head."""
    s = reset_state(jax.random.PRNGKey(5), PARAMS)
    s = s.replace(x=s.x.at[1].set(s.x[0] + 40.0), y=s.y.at[1].set(s.y[0] - 70.0))
    for t in range(30):
        s, *_ = step_state(jax.random.PRNGKey(t), s, LEFT, PARAMS)
    return s


def test_the_heading_camera_is_the_north_camera_turned_with_the_player(turning_state):
    """Heading up the screen (heading -pi/2) the two cameras see the same frame; heading east
    (0), the heading camera's frame is the north camera's turned a quarter counter-clockwise:
    what lies ahead (east) is up, what lies to the right (south) is right. Both draw the
    background by other formulas (separable waves, rank-6 turned waves), and every disc."""
    heading = Slither(camera="heading")
    up = _turned_player(turning_state, -math.pi / 2)
    np.testing.assert_allclose(np.asarray(heading.get_obs(up, PARAMS)), np.asarray(get_obs(up)), atol=2e-5)
    east = _turned_player(turning_state, 0.0)
    north_frame, heading_frame = np.asarray(get_obs(east)), np.asarray(heading.get_obs(east, PARAMS))
    # view pixel (row i, column j) lies 2i - 149 behind and 2j - 149 right of the head: the
    # north frame's pixel (row j, column 149 - i)
    np.testing.assert_allclose(heading_frame, np.rot90(north_frame, k=1), atol=2e-5)
    assert np.abs(heading_frame - north_frame).mean() > 0.01  # and they differ
    # The body trails behind the head: below the centre of the heading camera's frame.
    body = heading.get_obs(east.replace(pellet_value=jnp.zeros_like(east.pellet_value)), PARAMS.replace(
        background_contrast=np.float32(0.0)))
    body = np.asarray(body) > 0.5
    rows = np.nonzero(body[60:90, 60:90])[0] + 60
    assert rows.size and rows.min() >= 70 and rows.max() > 80


def test_the_heading_cameras_fast_observation_matches_its_preprocessed_raw_frame(turning_state):
    heading = Slither(camera="heading")
    for angle in (0.3, 2.0, 4.4):
        s = _turned_player(turning_state, angle)
        diff = np.abs(np.asarray(heading.get_obs(s, PARAMS)) - preprocess(np.asarray(heading.render_raw(s, PARAMS))))
        assert diff.mean() < 0.005 and (diff > 0.05).mean() < 0.02 and diff.max() < 0.25
        assert bool(heading.in_view(s)[1])  # 80 raw pixels from the head, in view whichever way it heads


def test_an_unknown_camera_is_refused():
    with pytest.raises(ValueError, match="unknown camera 'south'; choose one of north, heading"):
        Slither(camera="south")


def test_preprocess_numbers_options_and_backends():
    frame = np.zeros((300, 500, 3), np.uint8)
    frame[0, 100, 0] = 255
    frame[1, 101, 2] = 255
    frame[0, 99, 1] = 255
    out = preprocess(frame)
    assert out.shape == (150, 150) and out.dtype == np.float32
    assert out[0, 0] == pytest.approx(0.25)
    assert out.sum() == pytest.approx(0.25)
    batch = np.random.default_rng(0).integers(0, 256, (2, 3, 300, 500, 3), dtype=np.uint8)
    np_out = preprocess(batch)
    jnp_out = np.asarray(preprocess(jnp.asarray(batch)))
    assert np_out.shape == (2, 3, 150, 150)
    np.testing.assert_allclose(np_out, jnp_out, atol=1e-6)
    expected = batch[..., :, 100:400, :].reshape(2, 3, 150, 2, 150, 2, 3).mean(axis=(3, 5)).max(-1) / 255
    np.testing.assert_allclose(np_out, expected, atol=1e-6)
    small = preprocess(batch[0, 0], crop=central_crop(300, 500, (200, 400)), out_size=(50, 100))
    assert small.shape == (50, 100)
    floats = preprocess(batch[0, 0].astype(np.float32) / 255.0, crop=None, out_size=(100, 100))
    assert floats.shape == (100, 100) and 0.0 <= floats.min() and floats.max() <= 1.0
    with pytest.raises(ValueError):
        preprocess(frame, crop=(0, 0, 300, 300), out_size=(160, 150))
    with pytest.raises(ValueError):
        preprocess(frame, crop=(0, 300, 300, 300))


def test_preprocess_wrapper_on_rgb_observations():
    env = envs.PreprocessObservation(gym.make("cdrl/Slither-v0", obs_type="rgb"))
    assert env.observation_space.shape == (150, 150, 1)
    obs, _ = env.reset(seed=5)
    fast, _ = gym.make("cdrl/Slither-v0").reset(seed=5)
    assert obs.shape == (150, 150, 1) and obs.dtype == np.float32
    assert np.abs(obs - fast).mean() < 0.005


def test_behaviour_policy_switches_rarely_and_never_accelerates():
    def roll(key):
        def body(state, k):
            action, state = behaviour_step(k, state, None)
            return state, (action, state.behaviour)
        return jax.lax.scan(body, behaviour_init(key), jax.random.split(key, 2000))[1]

    actions, behaviour = jax.jit(jax.vmap(roll))(jax.random.split(jax.random.PRNGKey(0), 8))
    actions, behaviour = np.asarray(actions), np.asarray(behaviour)
    assert (actions[..., 2] == 0).all()
    rows = {tuple(r) for r in actions.reshape(-1, 3)}
    assert rows <= {tuple(r) for r in np.asarray(BEHAVIOURS)} and len(rows) == 4
    changes = (np.diff(behaviour, axis=1) != 0).mean()
    assert 0.003 < changes < 0.015


def test_uniform_policy_values():
    def roll(key):
        return jax.lax.scan(lambda s, k: uniform_step(k, s, None)[::-1],
                            uniform_init(key), jax.random.split(key, 3000))[1]

    a = np.asarray(jax.jit(roll)(jax.random.PRNGKey(1)))
    assert a.shape == (3000, 3) and a.dtype == np.float32
    assert a.min() >= 0.0 and a.max() < 1.0
    assert np.abs(a.mean(axis=0) - 0.5).max() < 0.03
    assert abs(np.corrcoef(a[:-1, 0], a[1:, 0])[0, 1]) < 0.1


def test_held_uniform_policy_holds_uniform_buttons_for_five_steps_on_average():
    """New buttons with probability 0.2 a step (a draw drawn again equal has chance 0), each
    uniform in [0, 1]; between draws the buttons stay as they were."""
    def roll(key):
        return jax.lax.scan(lambda s, k: held_uniform_step(k, s, None)[::-1],
                            held_uniform_init(key), jax.random.split(key, 5000))[1]

    a = np.asarray(jax.jit(roll)(jax.random.PRNGKey(2)))
    changed = (np.diff(a, axis=0) != 0).any(axis=1)
    assert abs(changed.mean() - HOLD_SWITCH_PROB) < 0.02
    draws = np.concatenate([a[:1], a[1:][changed]])
    assert draws.min() >= 0.0 and draws.max() < 1.0 and np.abs(draws.mean(axis=0) - 0.5).max() < 0.04
    assert ((np.diff(a, axis=0) != 0).all(axis=1) == changed).all()  # a new draw changes every button


def test_fastrng_keys_are_independent():
    u = np.asarray(fastrng.uniform(jax.random.PRNGKey(0), 20000))
    assert abs(u.mean() - 0.5) < 0.01 and abs(u.var() - 1 / 12) < 0.005
    keys = fastrng.split(jax.random.PRNGKey(0), 3)
    draws = [np.asarray(fastrng.uniform(k, 5000)) for k in keys]
    assert abs(np.corrcoef(draws[0], draws[1])[0, 1]) < 0.05
    assert not np.array_equal(np.asarray(fastrng.fold_in(keys[0], 1)), np.asarray(fastrng.fold_in(keys[0], 2)))


def test_vector_env_steps_all_games_and_autoresets():
    venv = gym.make_vec("cdrl/Slither-v0", num_envs=3, vectorization_mode="vector_entry_point", max_steps=2)
    obs, _ = venv.reset(seed=0)
    assert obs.shape == (3, 150, 150, 1)
    a = np.zeros((3, 3), np.float32)
    _, _, term, trunc, _ = venv.step(a)
    assert not (term | trunc).any()
    obs2, _, term, trunc, info = venv.step(a)
    assert trunc.all()
    obs3, rew, term, trunc, info = venv.step(a)
    assert not (term | trunc).any() and (rew == 0).all()
    assert np.abs(obs3 - obs2).mean() > 0.01
    np.testing.assert_allclose(info["length"], PARAMS.init_length)
    # The games restarted: their step count begins again, so they run 2 more steps before
    # being truncated again (games that merely went on would be truncated at once).
    _, _, term, trunc, _ = venv.step(a)
    assert not (term | trunc).any()
    _, _, term, trunc, _ = venv.step(a)
    assert trunc.all()


def test_move_bodies_follows_the_path_for_any_speed():
    x = jnp.arange(8, dtype=jnp.float32)[None, ::-1] * 6.0 + 100.0
    y = jnp.full((1, 8), 50.0)
    move = jax.jit(move_bodies, static_argnums=(4, 5))
    for speed in (2.0, 6.0, 9.0):
        nx, ny = move(x, y, jnp.zeros(1), jnp.full((1,), speed), 6.0, 1000.0)
        np.testing.assert_allclose(np.asarray(nx), np.asarray(x) + speed, atol=1e-4)
        np.testing.assert_allclose(np.asarray(ny), np.asarray(y), atol=1e-5)


def test_slither_params_is_a_traced_friendly_pytree():
    leaves = jax.tree.leaves(PARAMS)
    assert len(leaves) == len(SlitherParams.__dataclass_fields__)
    with pytest.raises(ValueError):
        Slither(arena_size=1000.0, pellet_cell_size=30.0)
