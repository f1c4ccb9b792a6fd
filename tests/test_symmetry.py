"""The north-up game's symmetries (envs.symmetry) against the game itself: the world turned or
mirrored about the player's head renders as the turned or mirrored frame, its physics under a
mirror swap the turn buttons, a frame turned by the heading is the heading camera's, and the
optical flow of two frames points along the heading, and the flow camera turns its frames by it."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdrl.data.frames import resize_obs
from envs import symmetry
from envs.render import wrap_delta, wrap_position
from envs.flow_view import FlowView
from envs.slither import Slither, SlitherState, level_params


def _transformed_world(game, state, quarter_turns, mirror):
    """The state with every snake moved to its offsets from the player's head under the
    transform (positions and headings), the pellets left as they are."""
    hx, hy = state.x[0, 0], state.y[0, 0]
    dx, dy = wrap_delta(state.x - hx, game.arena_size), wrap_delta(state.y - hy, game.arena_size)
    dx, dy = symmetry.transform_offsets(dx, dy, quarter_turns, mirror)
    ux, uy = symmetry.transform_offsets(jnp.cos(state.heading), jnp.sin(state.heading), quarter_turns, mirror)
    return state.replace(x=wrap_position(hx + dx, game.arena_size), y=wrap_position(hy + dy, game.arena_size),
                         heading=jnp.arctan2(uy, ux))


@pytest.fixture(scope="module")
def snakes_only():
    """A game, its flat level's physics (no background texture) and a state after 30 steps
    with every pellet removed: the frame holds only snakes, which a turn of the world moves
    anywhere (pellets live on the grid of cells)."""
    game, params = Slither(num_opponents=8), level_params("flat")
    _, state = game.reset(jax.random.PRNGKey(3), params)
    for t in range(30):
        _, state, *_ = game.jit.step(jax.random.PRNGKey(100 + t), state, jnp.array([t % 3 == 0, False, False]), params)
    empty = jnp.zeros_like(state.pellet_value)
    return game, params, state.replace(pellet_value=empty, pellet_dx=empty, pellet_dy=empty)


@pytest.mark.parametrize("quarter_turns,mirror", [(1, False), (2, False), (3, False), (0, True), (1, True), (3, True)])
def test_a_transformed_world_renders_as_the_transformed_frame(snakes_only, quarter_turns, mirror):
    game, params, state = snakes_only
    frame = game.get_obs(state, params)
    moved = game.get_obs(_transformed_world(game, state, quarter_turns, mirror), params)
    assert float(jnp.max(frame)) > 0.5  # snakes are in view
    # float32 positions near 1000 move a disc edge by up to 1e-4
    np.testing.assert_allclose(symmetry.transform_frame(frame, quarter_turns, mirror), moved, atol=1e-4)
    # and not trivially: the frame is not symmetric by itself
    assert float(jnp.max(jnp.abs(symmetry.transform_frame(frame, quarter_turns, mirror) - frame))) > 0.3


def test_a_mirrored_world_turns_the_other_way_on_the_swapped_button(snakes_only):
    """Right in the world is left in its mirror image: stepping the mirrored world with the
    buttons swapped moves the player's body to the mirror image of where the original goes."""
    game, params, state = snakes_only
    mirrored = _transformed_world(game, state, 0, True)
    buttons = jnp.array([1.0, 0.0, 1.0])  # turn right, accelerate
    key = jax.random.PRNGKey(0)
    after, _, _, _, _ = game.step_state(key, state, buttons, params)
    after_m, _, _, _, _ = game.step_state(key, mirrored, symmetry.transform_buttons(buttons, True), params)
    hx, hy = state.x[0, 0], state.y[0, 0]
    dx = wrap_delta(after.x[0] - hx, game.arena_size)
    dy = wrap_delta(after.y[0] - hy, game.arena_size)
    np.testing.assert_allclose(wrap_delta(after_m.x[0] - hx, game.arena_size), -dx, atol=1e-3)
    np.testing.assert_allclose(wrap_delta(after_m.y[0] - hy, game.arena_size), dy, atol=1e-3)
    # unswapped, the mirror image turns the other way: the heads part
    wrong, _, _, _, _ = game.step_state(key, mirrored, buttons, params)
    assert abs(float(wrap_delta(wrong.y[0, 0] - after_m.y[0, 0], game.arena_size))) > 0.5


def test_the_eight_transforms_are_d4():
    """Distinct on a generic frame, closed under composition (a turn after a mirror is a
    mirror after the opposite turn), and the symmetrised logits are invariant."""
    frame = jax.random.uniform(jax.random.PRNGKey(0), (6, 6))
    images = symmetry.all_transforms(frame)
    flat = np.asarray(images).reshape(8, -1)
    assert len({tuple(np.round(r, 6)) for r in flat}) == 8
    for k, m in symmetry.TRANSFORMS:
        twice = symmetry.transform_frame(symmetry.transform_frame(frame, k, m), (-k) % 4 if not m else k, m)
        np.testing.assert_allclose(twice, frame)  # every transform has its inverse among the eight
    # a policy read through symmetrised_logits gives the same buttons on every transform of the
    # frame, the turn buttons swapped on the mirrored ones
    w = jax.random.normal(jax.random.PRNGKey(1), (36, 3))

    @jax.jit
    def policy(f):
        return symmetry.symmetrised_logits(symmetry.all_transforms(f).reshape(8, -1) @ w)

    base = policy(frame)
    assert float(jnp.max(jnp.abs(base[:2] - base[1::-1]))) > 1e-3  # not symmetric in the buttons by accident
    for k, m in symmetry.TRANSFORMS:
        np.testing.assert_allclose(policy(symmetry.transform_frame(frame, k, m)),
                                   symmetry.transform_buttons(base, m), rtol=1e-5, atol=1e-5)


def test_augment_swaps_only_the_mirrored_buttons():
    frames = jnp.broadcast_to(jnp.arange(16.0).reshape(4, 4), (64, 4, 4))
    buttons = jnp.broadcast_to(jnp.array([1.0, 0.0, 1.0]), (64, 3))
    out_frames, out_buttons = symmetry.augment(jax.random.PRNGKey(0), frames, buttons)
    mirrored = np.asarray(out_buttons[:, 0] == 0.0)
    assert 10 < mirrored.sum() < 54
    np.testing.assert_array_equal(np.asarray(out_buttons)[mirrored], [[0.0, 1.0, 1.0]] * int(mirrored.sum()))
    for f, m in zip(np.asarray(out_frames), mirrored):  # each frame is one of the four turns of its mirror
        source = np.asarray(frames[0])[:, ::-1] if m else np.asarray(frames[0])
        assert any(np.array_equal(f, np.rot90(source, k)) for k in range(4))


def test_frames_must_be_square():
    with pytest.raises(ValueError, match="square"):
        symmetry.transform_frame(jnp.zeros((4, 6)), 1, False)


def test_quarter_turn_offsets_match_rot90():
    """transform_offsets' convention against numpy's rot90 on an image with one lit pixel."""
    n = 5
    image = np.zeros((n, n))
    r, c = 1, 4  # dy = r - 2, dx = c - 2 from the centre
    image[r, c] = 1.0
    for k in range(4):
        for m in (False, True):
            dx, dy = symmetry.transform_offsets(c - 2.0, r - 2.0, k, m)
            turned = np.asarray(symmetry.transform_frame(jnp.asarray(image), k, m))
            assert turned[int(dy) + 2, int(dx) + 2] == 1.0, (k, m)


def test_turn_to_heading_gives_the_heading_cameras_view():
    """A north-up frame turned by the player's heading is the heading camera's frame of the same
    state (64 x 64, inside the disc both hold; bilinear resampling blurs a little), and turning by
    the mirrored heading is not."""
    params = level_params("thesis")
    north, heading_up = Slither(), Slither(camera="heading")
    _, state = north.reset(jax.random.PRNGKey(5), params)
    for t in range(20):
        _, state, *_ = north.step(jax.random.PRNGKey(t), state, jnp.array([t % 4 == 0, 0.0, 0.0]), params)
    frame = resize_obs(north.get_obs(state, params), 64)
    expected = np.asarray(resize_obs(heading_up.get_obs(state, params), 64))
    c, s = jnp.cos(state.heading[0]), jnp.sin(state.heading[0])
    q = np.arange(64) - 31.5
    disc = np.hypot(*np.meshgrid(q, q)) < 28

    def error(xy):
        turned = np.asarray(symmetry.turn_to_heading(frame[None], jnp.asarray([xy]))[0])
        return float(np.abs(turned - expected)[disc].mean())

    assert error([c, s]) < 0.006
    assert error([3.0 * c, 3.0 * s]) < 0.006  # any length
    assert error([c, -s]) > 0.03  # the north-up frame itself is 0.049 away


def test_heading_from_flow_reads_the_heading_off_two_frames():
    """On games of random play (level thesis, 64 x 64), the flow between o_t and o_{t+1} points
    along the heading the step between them moved with, to a few degrees (what a network trained
    on the heading itself reaches: about 1.5 degrees); the unmasked flow, the player's body
    included, does worse, a frame against itself says nothing, and refits that weigh down the
    pixels one translation does not explain (other snakes) cut the tail."""
    game, params = Slither(), level_params("thesis")

    def one(key):
        k_reset, k_run = jax.random.split(key)
        obs, state = game.reset(k_reset, params)

        def body(c, k):
            state, obs = c
            k_act, k_env = jax.random.split(k)
            buttons = (jax.random.uniform(k_act, (3,)) < jnp.array([0.3, 0.3, 0.1])).astype(jnp.float32)
            nxt, state, _, term, _, _ = game.step(k_env, state, buttons, params)
            return (state, nxt), (resize_obs(obs, 64), resize_obs(nxt, 64), state.heading[0], term)

        return jax.lax.scan(body, (state, obs), jax.random.split(k_run, 40))[1]

    before, after, heading, term = jax.jit(jax.vmap(one))(jax.vmap(jax.random.PRNGKey)(jnp.arange(6)))
    alive = ~np.asarray(jnp.cumsum(term, axis=1) > 0).reshape(-1)

    def errors(xy):
        xy = np.asarray(xy).reshape(-1, 2)[alive]
        d = np.arctan2(xy[:, 1], xy[:, 0]) - np.asarray(heading).reshape(-1)[alive]
        return np.degrees(np.abs(np.angle(np.exp(1j * d))))

    read = errors(symmetry.heading_from_flow(before, after))
    assert alive.sum() > 150
    assert np.median(read) < 4.0 and np.percentile(read, 90) < 12.0
    assert np.median(errors(symmetry.heading_from_flow(before, after, inner_radius=0.0))) > np.median(read)
    assert np.all(np.asarray(symmetry.heading_from_flow(after, after)) == 0.0)
    robust = errors(symmetry.heading_from_flow(before, after, reweightings=3))  # other snakes weighed down
    assert np.percentile(robust, 90) < 0.3 * np.percentile(read, 90)  # measured: 0.8 against 7.4 degrees


def test_the_flow_camera_shows_the_heading_cameras_view_from_the_pixels():
    """The `flow` view (a wrapper) plays the north-up game (the same states and rewards step for step) and
    shows its first frame north-up, every later one turned by the heading the pixels show: the
    heading camera's frame of the same state but for that reading's error (64 x 64, inside the
    disc both hold), where the north-up frame is far from it."""
    params = level_params("thesis")
    flow, north, heading_up = FlowView(Slither()), Slither(), Slither(camera="heading")
    plain = [f.name for f in dataclasses.fields(SlitherState)]

    def one(key):
        k_reset, k_run = jax.random.split(key)
        obs, state = flow.reset(k_reset, params)
        north_state = north.reset_state(k_reset, params)

        def body(c, k):
            state, north_state = c
            k_act, k_env = jax.random.split(k)
            buttons = (jax.random.uniform(k_act, (3,)) < jnp.array([0.3, 0.3, 0.1])).astype(jnp.float32)
            obs, state, reward, term, _, _ = flow.step(k_env, state, buttons, params)
            north_state, north_reward, *_ = north.step_state(k_env, north_state, buttons, params)
            game_state = SlitherState(**{name: getattr(state, name) for name in plain})
            same = jnp.all(jnp.stack([jnp.all(getattr(state, n) == getattr(north_state, n)) for n in plain]))
            frames = [resize_obs(o, 64) for o in (obs, heading_up.get_obs(game_state, params),
                                                 north.get_obs(game_state, params))]
            return (state, north_state), (same & (reward == north_reward), term, *frames)

        first = (resize_obs(obs, 64), resize_obs(north.get_obs(north_state, params), 64))
        return first, jax.lax.scan(body, (state, north_state), jax.random.split(k_run, 30))[1]

    (first, first_north), (same, term, shown, heading_view, north_view) = jax.jit(jax.vmap(one))(
        jax.vmap(jax.random.PRNGKey)(jnp.arange(4)))
    np.testing.assert_allclose(first, first_north, atol=1e-4)  # the heading camera's drawing, turned by nothing
    assert np.all(np.asarray(same))
    alive = ~np.asarray(jnp.cumsum(term, axis=1) > 0)
    q = np.arange(64) - 31.5
    disc = np.hypot(*np.meshgrid(q, q)) < 28

    def error(a, b):
        return np.abs(np.asarray(a) - np.asarray(b))[..., disc].mean(-1)[alive]

    assert alive.sum() > 80
    to_heading, to_north = error(shown, heading_view), error(north_view, heading_view)
    assert np.median(to_heading) < 0.005 and np.percentile(to_heading, 90) < 0.01  # measured: 0.003, 0.007
    assert np.median(to_north) > 0.03


@pytest.mark.parametrize("streams", [4, 3])
def test_an_offline_run_with_mirror_streams_sees_half_its_streams_in_a_mirror(streams):
    """`--mirror-streams`: the loss of a chunk is the plain loss of the chunk whose second half
    of streams was mirrored by hand (columns reversed, right and left swapped); an online run is
    refused by name."""
    from cdrl.data.stream import Chunk
    from cdrl.models import TINY, make_variant
    from cdrl.runs.config import RunConfig
    from cdrl.training.optim import HParams
    from cdrl.training.step import chunk_loss

    v = make_variant("reward_prediction", TINY)
    params = v.init(jax.random.PRNGKey(0))
    rng = np.random.default_rng(0)
    t, s = 5, TINY.image_size
    frames = rng.uniform(size=(t + 1, streams, s, s)).astype(np.float32)
    action = (rng.uniform(size=(t, streams, 3)) > 0.5).astype(np.float32)
    reward = rng.normal(size=(t, streams)).astype(np.float32)
    first = np.zeros((t, streams), bool)
    first[0] = True
    chunk = Chunk(obs=frames[:-1], next_obs=frames[1:], action=action, reward=reward, is_first=first)
    by_hand = frames.copy()
    buttons = action.copy()
    for b in range(streams // 2 + streams % 2, streams):  # the last B // 2 streams
        by_hand[:, b] = frames[:, b, :, ::-1]
        buttons[:, b] = action[:, b][:, [1, 0, 2]]
    mirrored = Chunk(obs=by_hand[:-1], next_obs=by_hand[1:], action=buttons, reward=reward, is_first=first)
    carry = v.init_carry(streams)
    loss, _ = chunk_loss(v, params, carry, HParams.create(v, mirror=True), chunk)
    expected, _ = chunk_loss(v, params, carry, HParams.create(v), mirrored)
    np.testing.assert_allclose(float(loss), float(expected), rtol=1e-6)
    unmirrored, _ = chunk_loss(v, params, carry, HParams.create(v), chunk)
    assert abs(float(unmirrored) - float(loss)) > 1e-6  # the mirror changed what the model saw
    assert RunConfig(variant="main", mirror_streams=True).hparams(make_variant("main", TINY)).mirror
    with pytest.raises(ValueError, match="mirror_streams"):
        RunConfig(variant="final_proposal", learner="imagination_ac", mirror_streams=True)
