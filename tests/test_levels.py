"""The built-in game's levels: the background contrast knob is a linear blend toward the
mean brightness, levels are named overrides, and a run's level reaches the data it trains on."""
import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdrl.runs.config import RunConfig
from cdrl.runs.sources import game_params, load_episodes
from envs.slither import LEVELS, Slither, level_params


@pytest.fixture(scope="module")
def background_only():
    """A state whose view holds no pellet and no opponent: away from the player's own body
    (near the view's centre) every pixel is background."""
    game = Slither()
    state = game.reset_state(jax.random.PRNGKey(3), game.default_params)
    far = state.x[0, 0] + game.arena_size / 2
    state = state.replace(pellet_value=jnp.zeros_like(state.pellet_value),
                          x=state.x.at[1:].set(far % game.arena_size))
    return game, state


def test_contrast_blends_the_background_toward_its_mean(background_only):
    game, state = background_only
    obs = {c: np.asarray(game.get_obs(state, level_params("thesis").replace(background_contrast=np.float32(c))))
           for c in (0.0, 0.5, 1.0)}
    corner = (slice(0, 30), slice(0, 30))  # 60 raw pixels from the head: no body there
    flat, half, full = (obs[c][corner] for c in (0.0, 0.5, 1.0))
    assert np.ptp(flat) < 1e-6  # no texture at contrast 0
    assert np.ptp(full) > 0.05  # the hexagons at 1
    np.testing.assert_allclose(half, (flat + full) / 2, atol=1e-5)
    # The raw frame follows the same knob.
    raw0 = np.asarray(game.render_raw(state, level_params("flat")))[:60, :60]
    assert np.ptp(raw0.reshape(-1, 3), axis=0).max() <= 1


def test_levels_are_named_overrides():
    assert LEVELS["thesis"] == {}
    assert [RunConfig(level=name).level for name in LEVELS] == list(LEVELS)  # one list of levels: the game's
    listed = "thesis, flat, sparse, clean, visible, turned-true-visible, turned-true, turned-redrawn, turned"
    with pytest.raises(ValueError, match=f"level must be one of {listed}; got 'hard'"):
        RunConfig(level="hard")
    clean = level_params("clean")
    assert float(clean.background_contrast) == 0.0 and float(clean.pellet_init_fill) < 0.2
    with pytest.raises(ValueError, match="unknown game level 'hard'; choose one of"):
        level_params("hard")
    cfg = RunConfig(level="flat", env="pellet_init_fill=0.3")
    params = game_params(cfg)
    assert float(params.background_contrast) == 0.0 and float(params.pellet_init_fill) == pytest.approx(0.3)
    with pytest.raises(ValueError, match="bad game parameter 'speed=fast'"):
        game_params(dataclasses.replace(cfg, env="speed=fast"))


def test_a_runs_level_reaches_its_data(tmp_path):
    """The cached data set of a level is its own (a flat background has less spread) and its
    manifest records the level's game parameters."""
    base = dict(preset="small", episodes=2, episode_steps=8, data="game")
    spread = {}
    for level in ("thesis", "flat"):
        train, _ = load_episodes(RunConfig(level=level, **base), tmp_path)
        frames = np.concatenate([train[i].frames for i in range(len(train))]).astype(np.float32) / 255
        spread[level] = float(np.median(frames.std(axis=(1, 2))))
    assert spread["flat"] < 0.95 * spread["thesis"], spread
    dirs = sorted(p for p in tmp_path.iterdir())
    assert len(dirs) == 2 and dirs[1].name.endswith("-flat"), dirs
    manifest = json.loads((dirs[1] / "manifest.json").read_text())
    assert manifest["config"]["env_params"]["background_contrast"] == 0.0


def test_the_data_policy_plays_the_collected_episodes(tmp_path):
    """`data_policy` names the policy in the data set's manifest; by default a variant that acts
    gets uniform play, and `held_uniform` holds its buttons across steps."""
    base = dict(preset="tiny", episodes=2, episode_steps=30, data="game", variant="final_proposal",
                learner="world_model")
    held, _ = load_episodes(RunConfig(data_policy="held_uniform", **base), tmp_path)
    auto, _ = load_episodes(RunConfig(**base), tmp_path)
    policies = {json.loads((d / "manifest.json").read_text())["config"]["policy"] for d in tmp_path.iterdir()}
    assert policies == {"held_uniform", "uniform"}
    repeats = lambda eps: np.mean([(np.diff(eps[i].actions[:-1], axis=0) == 0).all(axis=1).mean()  # noqa: E731
                                   for i in range(len(eps))])
    assert repeats(held) > 0.6 and repeats(auto) < 0.1


def test_the_visible_level_draws_pellets_that_survive_the_small_preset(background_only):
    """Level `visible` is the thesis level's physics with pellets drawn at a snake segment's
    radius: one pellet in an empty view brightens the 64 x 64 frame by most of its range, the
    thesis level's by about a fifth, and the thesis level's as preset `small-max` sees it (a 5 x 5
    max filter before the shrinking) by most of its range too."""
    from cdrl.data.frames import model_obs, resize_obs
    from cdrl.models.arch import preset
    from cdrl.runs.sources import run_game
    from envs.slither import level_game

    _, state = background_only
    game, params = run_game(RunConfig(level="visible"))
    assert game.spec.pellet_radius == 6.0 and level_game("thesis").spec.pellet_radius == 2.0
    assert params == game_params(RunConfig(level="thesis")).replace(max_steps=params.max_steps)
    cell = game.pellet_cell_size
    head_cell = (int(state.y[0, 0] // cell), int(state.x[0, 0] // cell))
    iy, ix = head_cell[0] - 2, head_cell[1] - 2  # a cell 100 raw pixels up and left of the head
    one = state.replace(pellet_value=state.pellet_value.at[iy, ix].set(0.5),
                        pellet_dx=state.pellet_dx.at[iy, ix].set(cell / 2),
                        pellet_dy=state.pellet_dy.at[iy, ix].set(cell / 2))
    contrast = {}
    for level in ("thesis", "visible"):
        g = level_game(level)
        with_pellet = np.asarray(resize_obs(g.get_obs(one, params), 64))
        empty = np.asarray(resize_obs(g.get_obs(state, params), 64))
        corner = (slice(0, 24), slice(0, 24))  # the pellet's quarter, away from the player's body
        contrast[level] = float((with_pellet - empty)[corner].max())
    g = level_game("thesis")
    seen = [np.asarray(model_obs(g.get_obs(s, params), preset("small-max"))) for s in (one, state)]
    contrast["thesis, small-max"] = float((seen[0] - seen[1])[corner].max())
    assert contrast["visible"] > 0.6 and contrast["thesis"] < 0.3 and contrast["thesis, small-max"] > 0.6, contrast


def test_the_turned_true_visible_level_is_the_visible_level_seen_by_a_turning_camera(tmp_path):
    """Level `turned-true-visible` (old name `heading`): the visible level (the thesis level's
    physics), its camera turning with the player, in the runs that play it and in the data a run
    collects."""
    from cdrl.runs.sources import run_game

    game, params = run_game(RunConfig(level="turned-true-visible"))
    visible, visible_params = run_game(RunConfig(level="visible"))
    assert game.spec.camera == "heading" and visible.spec.camera == "north"
    assert dataclasses.replace(game.spec, camera="north") == visible.spec and params == visible_params
    base = dict(preset="small", episodes=2, episode_steps=8, data="game", variant="main_action")
    first = {}
    for level in ("visible", "turned-true-visible"):
        train, _ = load_episodes(RunConfig(level=level, **base), tmp_path)
        first[level] = train[0]
    # the same games and actions (the same seed), other frames
    np.testing.assert_array_equal(first["visible"].actions, first["turned-true-visible"].actions)
    assert np.abs(first["visible"].frames.astype(int) - first["turned-true-visible"].frames).mean() > 5
