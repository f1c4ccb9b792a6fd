"""`cdrl collect DIR --env ID`: any registered gymnasium game as a data set (CartPole-v1's
Discrete actions one-hot, Pendulum-v1's Box actions rescaled, both recorded from their
rendered frames), and `cdrl train --data DIR` on it, the action variants sized from it."""
import importlib.util
import json
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from cdrl.cli import main as cli_main
from cdrl.data import gymrec
from cdrl.data.gymrec import action_codec, make_env, parse_env_kwargs
from cdrl.data.store import EpisodeDataset, load_episode
from cdrl.runs.config import upgrade
from envs.preprocess import preprocess

TRAIN = ["--preset", "tiny", "--unroll", "4", "--batch", "2", "--steps", "3", "--eval-episodes", "1",
         "--checkpoint-every", "3"]


def test_action_codecs_map_to_and_from_the_unit_interval():
    rng = np.random.default_rng(0)
    discrete = action_codec(gym.spaces.Discrete(4, start=1))
    assert discrete.dim == 4 and discrete.decode(np.array([0.1, 0.2, 0.9, 0.3])) == 3
    samples = np.stack([discrete.sample(rng) for _ in range(200)])
    assert set(samples.sum(axis=1)) == {1.0} and set(samples.argmax(axis=1)) == {0, 1, 2, 3}
    box = action_codec(gym.spaces.Box(low=np.array([-2.0, 0.0], np.float32), high=np.array([2.0, 10.0], np.float32)))
    assert box.dim == 2
    np.testing.assert_allclose(box.decode(np.array([0.5, 1.0])), [0.0, 10.0])
    np.testing.assert_allclose(box.decode(np.array([0.0, 0.25])), [-2.0, 2.5])
    assert all(0 <= v <= 1 for _ in range(50) for v in box.sample(rng))
    assert action_codec(gym.spaces.MultiBinary(3)).decode(np.array([0.2, 0.7, 0.5])).tolist() == [0, 1, 0]
    with pytest.raises(ValueError, match="unbounded values"):
        action_codec(gym.spaces.Box(low=-np.inf, high=np.inf, shape=(2,)))
    with pytest.raises(ValueError, match=r"action space MultiDiscrete\(\[2 3\]\) is not supported"):
        action_codec(gym.spaces.MultiDiscrete([2, 3]))


def test_env_kwargs_parse_as_json_or_key_value_pairs():
    assert parse_env_kwargs(['{"is_slippery": false, "map_name": "8x8"}']) == {"is_slippery": False, "map_name": "8x8"}
    assert parse_env_kwargs(["is_slippery=false", "map_name=8x8,g=9.5"]) == {"is_slippery": False, "map_name": "8x8",
                                                                             "g": 9.5}
    with pytest.raises(ValueError, match="bad --env-kwargs item 'slippery'"):
        parse_env_kwargs(["slippery"])


def _replays(out, env_id: str, decode) -> None:
    """Each recorded episode is what the game gives when it is reset with the recording's seed
    and fed the decoded recorded actions: the env got what was recorded."""
    manifest = json.loads((out / "manifest.json").read_text())
    crop, size = tuple(manifest["config"]["preprocess"]["crop"]), tuple(manifest["config"]["preprocess"]["out_size"])
    env = make_env(env_id, "render", manifest["config"]["env_kwargs"])
    for entry in manifest["episodes"][:3]:
        episode = load_episode(out / entry["file"])
        obs, _ = env.reset(seed=entry["index"])
        for t in range(len(episode) - 1):
            frame = np.round(preprocess(obs, crop, size) * 255).astype(np.uint8)
            np.testing.assert_array_equal(frame, episode.frames[t])
            obs, *_ = env.step(decode(episode.actions[t]))
    env.close()


def test_collect_cartpole_from_its_rendered_frames_and_train_on_it(tmp_path, capsys):
    out = tmp_path / "cartpole"
    assert cli_main(["collect", str(out), "--env", "CartPole-v1", "--obs", "render", "--obs-size", "16",
                     "--episodes", "10", "--episode-steps", "25"]) == 0
    data = EpisodeDataset(out, "all")
    data.verify()
    assert data.complete and len(data) == 10 and data.manifest["data"] == {
        "action_dim": 2, "frame_dtype": "uint8", "frame_shape": [16, 16]}
    actions = np.concatenate([e.actions for e in data])
    assert set(actions.sum(axis=1)) == {1.0} and set(actions.argmax(axis=1)) == {0, 1}  # one-hot, both actions
    frames = np.concatenate([e.frames for e in data])
    assert frames.std() > 0  # the cart and the pole, not a blank frame
    _replays(out, "CartPole-v1", lambda a: int(np.argmax(a)))

    for variant in ("main", "main_action"):
        run = tmp_path / variant
        capsys.readouterr()
        assert cli_main(["train", "--run-dir", str(run), "--data", str(out), "--variant", variant, *TRAIN]) == 0, \
            capsys.readouterr().err
        assert upgrade(json.loads((run / "config.json").read_text()))["action_dim"] == 2
        assert [json.loads(line)["step"] for line in (run / "metrics.jsonl").read_text().splitlines()] == [0, 1, 2]
    assert cli_main(["eval", str(tmp_path / "main_action")]) == 0  # its checkpoint restores with the 2-action encoder


def test_collect_box_actions_of_pendulum_rescaled_from_their_bounds(tmp_path):
    out = tmp_path / "pendulum"
    assert cli_main(["collect", str(out), "--env", "Pendulum-v1", "--obs", "render", "--obs-size", "16",
                     "--episodes", "3", "--episode-steps", "8", "--env-kwargs", "g=9.81"]) == 0
    data = EpisodeDataset(out, "all")
    assert data.manifest["data"]["action_dim"] == 1
    assert data.manifest["config"]["env_kwargs"] == {"g": 9.81}
    actions = np.concatenate([e.actions for e in data])
    assert actions.min() >= 0 and actions.max() <= 1 and actions.std() > 0.1
    _replays(out, "Pendulum-v1", lambda a: (-2.0 + 4.0 * a.astype(np.float64)).astype(np.float32))


def test_a_game_named_in_gymnasiums_module_form_and_an_unknown_namespace(tmp_path, capsys):
    env = make_env("gymnasium.envs.classic_control.cartpole:CartPole-v1", "render")
    try:
        assert env.spec.id == "CartPole-v1" and env.action_space == gym.spaces.Discrete(2)
        assert env.observation_space.shape == (400, 600, 3)
    finally:
        env.close()
    with pytest.raises(ValueError, match="importing no_such_module, which registers it, failed: No module named"):
        make_env("no_such_module:CartPole-v1", "render")
    with pytest.raises(ValueError, match=r"Namespace Nope not found.* name it in the id: --env MODULE:Nope/Game-v0 "
                                         r"\(gymnasium's module:ID form\)"):
        make_env("Nope/Game-v0")
    capsys.readouterr()
    assert cli_main(["collect", str(tmp_path / "nope"), "--env", "Nope/Game-v0", "--episodes", "1"]) == 2
    assert "--env MODULE:Nope/Game-v0 (gymnasium's module:ID form)" in capsys.readouterr().err
    if importlib.util.find_spec("ale_py") is None:
        with pytest.raises(ValueError, match=r"Namespace ALE not found.*: pip install ale-py$"):
            make_env("ALE/Pong-v5")
        with pytest.raises(ValueError, match=r"importing ale_py, which registers it, failed: .*\(pip install ale-py\)"):
            make_env("ale_py:ALE/Pong-v5")
    else:  # its package is imported first: no module:ID form needed
        make_env("ALE/Pong-v5").close()


def test_the_package_of_a_known_namespace_is_imported_before_its_game_is_made(monkeypatch):
    """`NAMESPACE_PACKAGES` (ALE -> ale_py) at work, with a module in tests/ that registers a
    game on import standing in for the package."""
    monkeypatch.syspath_prepend(str(Path(__file__).parent))
    from registers_games import GAME  # the game is unregistered and the module forgotten below

    namespace = GAME.partition("/")[0]
    try:
        gym.registry.pop(GAME)
        sys.modules.pop("registers_games")
        with pytest.raises(ValueError, match=f"Namespace {namespace} not found.*module:ID form"):
            make_env(GAME, "render")
        monkeypatch.setitem(gymrec.NAMESPACE_PACKAGES, namespace, ("no_such_games", "no-such-games"))
        with pytest.raises(ValueError, match=f"Namespace {namespace} not found.*: pip install no-such-games$"):
            make_env(GAME, "render")
        monkeypatch.setitem(gymrec.NAMESPACE_PACKAGES, namespace, ("registers_games", "registers-games"))
        env = make_env(GAME, "render")
        assert "registers_games" in sys.modules
        assert env.spec.id == GAME and env.observation_space.shape == (400, 600, 3)
        env.close()
    finally:
        gym.registry.pop(GAME, None)
        sys.modules.pop("registers_games", None)

