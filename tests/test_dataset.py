"""Tests of the on-disk episode data set: its format and reader (cdrl.data.store), atomic writes
(cdrl.data.atomic), the resumable writer (cdrl.data.writer), collection (cdrl.data.collect) and
recording (cdrl.data.gymrec)."""

from __future__ import annotations

import json
import os

import gymnasium as gym
import jax
import numpy as np
import pytest

from cdrl.data import store as ds
from cdrl.data.atomic import atomic_write, atomic_write_text
from cdrl.data.episode import Episode
from cdrl.data.lock import LOCK_NAME
from cdrl.data.collect import collect
from cdrl.data.gymrec import record_gym
from cdrl.data.store import DatasetError, EpisodeDataset, split_episodes
from cdrl.data.writer import Writer
from envs import fastrng
from envs.policies import get_policy
from envs.gym_env import game_for

SMALL = dict(policy="uniform", seed=7, max_steps=12, batch_size=4, chunk_steps=8, progress=False)


def small_collect(path, num_episodes=6, **overrides):
    return collect(path, num_episodes, **{**SMALL, **overrides})


@pytest.fixture(scope="module")
def collected(tmp_path_factory):
    path = tmp_path_factory.mktemp("collected")
    manifest = small_collect(path, num_episodes=10)
    return path, manifest


def load_all(path):
    return [(e.frames, e.actions, e.rewards) for e in EpisodeDataset(path, "all")]


def test_episode_validates_shapes_dtypes_and_ranges():
    n = 4
    good = dict(frames=np.zeros((n, 8, 8), np.uint8), actions=np.full((n, 3), 0.5, np.float32),
                rewards=np.zeros(n, np.float32))
    assert len(Episode(**good)) == n
    bad_cases = {
        "frames": dict(good, frames=np.zeros((n, 8), np.uint8)),
        "frames float": dict(good, frames=np.full((n, 8, 8), 1.5, np.float32)),
        "actions": dict(good, actions=np.zeros((n + 1, 3), np.float32)),
        "actions range": dict(good, actions=np.full((n, 3), 2.0, np.float32)),
        "actions dtype": dict(good, actions=np.zeros((n, 3), np.float64)),
        "rewards": dict(good, rewards=np.zeros(n - 1, np.float32)),
        "rewards finite": dict(good, rewards=np.full(n, np.nan, np.float32)),
    }
    for name, kwargs in bad_cases.items():
        with pytest.raises(ValueError, match=name.split()[0]):
            Episode(**kwargs)


def _replay(game, params, seed, index):
    """Episode `index` of a uniform-policy collection with `seed`, played one step at a time
    by the jitted game: its key is fold_in(PRNGKey(seed), index), split into reset, policy
    and run keys; every step splits the run key into (next, policy, game) keys. Returns the
    frames (uint8), actions and rewards (r_0 = 0), up to the frame that ends the game."""
    policy = get_policy("uniform")
    k_reset, k_policy, key = fastrng.split(fastrng.fold_in(jax.random.PRNGKey(seed), index), 3)
    obs, state = game.jit.reset(k_reset, params)
    pstate = policy.init(k_policy)
    frames, actions, rewards, done = [], [], [np.float32(0.0)], False
    while True:
        key, k_act, k_game = fastrng.split(key, 3)
        action, pstate = policy.step(k_act, pstate, obs)
        frames.append(np.round(np.asarray(obs) * 255).astype(np.uint8))
        actions.append(np.asarray(action, np.float32))
        if done:
            return np.stack(frames), np.stack(actions), np.asarray(rewards, np.float32)
        obs, state, reward, terminated, truncated, _ = game.jit.step(k_game, state, action, params)
        rewards.append(np.float32(reward))
        done = bool(terminated) or bool(truncated)


def test_round_trip_matches_the_game(collected):
    path, manifest = collected
    assert manifest["complete"] and len(manifest["episodes"]) == 10
    assert sorted(p.name for p in path.glob("episode_*.npz")) == [f"episode_{i:06d}.npz" for i in range(10)]
    data = EpisodeDataset(path, "all")
    assert len(data) == 10 and data.complete
    assert data.lengths == [e["length"] for e in manifest["episodes"]]
    game = game_for()
    params = game.default_params.replace(max_steps=np.int32(12))
    for i in (0, 9):
        ep = data[i]
        assert ep.frames.dtype == np.uint8 and ep.frames.shape[1:] == (150, 150)
        assert 2 <= len(ep) <= 13
        assert ep.actions.dtype == np.float32 and ep.actions.shape == (len(ep), 3)
        assert ((ep.actions > 0.02) & (ep.actions < 0.98)).any()
        assert ep.rewards[0] == 0.0
        # The whole episode, every frame, action and reward, against the game played step by
        # step (the collection ran batches of 4 games in chunks of 8 steps).
        frames, actions, rewards = _replay(game, params, 7, i)
        assert len(ep) == len(frames)
        np.testing.assert_array_equal(ep.frames, frames)
        np.testing.assert_array_equal(ep.actions, actions)
        np.testing.assert_array_equal(ep.rewards, rewards)
        if len(ep) == 13:
            assert manifest["config"]["max_steps"] == 12
        assert not np.array_equal(ep.frames[0], ep.frames[1])


def test_split_is_90_10_disjoint_and_seeded(tmp_path, collected):
    path, manifest = collected
    train, test = EpisodeDataset(path, "train"), EpisodeDataset(path, "test")
    assert len(train) == 9 and len(test) == 1
    assert set(train.indices) | set(test.indices) == set(range(10))
    assert not set(train.indices) & set(test.indices)
    s = split_episodes(100, 0.1, seed=3)
    assert len(s["test"]) == 10 and len(s["train"]) == 90
    assert s == split_episodes(100, 0.1, seed=3)
    assert s["test"] != split_episodes(100, 0.1, seed=4)["test"]
    assert manifest["split"] == split_episodes(10, 0.1, seed=7)


def test_interrupted_write_leaves_no_partial_episode(tmp_path, monkeypatch):
    real = ds._write_npz
    calls = []

    def dies_mid_write(f, episode, compress):
        calls.append(1)
        if len(calls) == 3:
            f.write(b"PK\x03\x04 half an episode")
            raise KeyboardInterrupt
        real(f, episode, compress)

    monkeypatch.setattr(ds, "_write_npz", dies_mid_write)
    with pytest.raises(KeyboardInterrupt):
        small_collect(tmp_path)
    names = sorted(p.name for p in tmp_path.iterdir() if p.name != LOCK_NAME)  # the lock file stays
    assert names == ["episode_000000.npz", "episode_000001.npz", "manifest.json"]
    for name in names[:2]:
        ds.load_episode(tmp_path / name)
    leftover = tmp_path / ".tmp-episode_000004.npz.abc"
    leftover.write_bytes(b"PK\x03\x04 killed while writing")
    assert len(EpisodeDataset(tmp_path, "all")) == 0
    monkeypatch.setattr(ds, "_write_npz", real)
    manifest = small_collect(tmp_path)
    assert manifest["complete"] and not leftover.exists()
    assert len(EpisodeDataset(tmp_path, "all")) == 6


def test_resume_skips_present_episodes_and_reproduces_them(tmp_path, monkeypatch):
    full = tmp_path / "full"
    part = tmp_path / "part"
    small_collect(full)
    real_write = Writer.write
    written = []

    def stop_after_five(self, index, episode, compress=True):
        if len(written) == 5:
            raise KeyboardInterrupt
        written.append(index)
        real_write(self, index, episode, compress)

    monkeypatch.setattr(Writer, "write", stop_after_five)
    with pytest.raises(KeyboardInterrupt):
        small_collect(part)
    listed = json.loads((part / "manifest.json").read_text())["episodes"]
    assert len(listed) == 4 and not json.loads((part / "manifest.json").read_text())["complete"]
    written.clear()
    monkeypatch.setattr(Writer, "write", lambda self, i, e, c=True: (written.append(i), real_write(self, i, e, c)))
    manifest = small_collect(part)
    assert written == [5]
    assert manifest["complete"] and len(manifest["episodes"]) == 6
    for a, b in zip(load_all(full), load_all(part)):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)


def test_corrupt_file_error_names_the_file(tmp_path):
    small_collect(tmp_path, num_episodes=2, max_steps=4)
    victim = tmp_path / "episode_000001.npz"
    victim.write_bytes(victim.read_bytes()[: victim.stat().st_size // 2])
    data = EpisodeDataset(tmp_path, "all")
    assert len(data[0]) >= 2
    with pytest.raises(DatasetError, match="episode_000001.npz"):
        data[1]
    with pytest.raises(DatasetError, match="episode_000001.npz"):
        data.verify()
    (tmp_path / "episode_000000.npz").write_bytes(b"not a zip")
    with pytest.raises(DatasetError, match="episode_000000.npz"):
        data[0]


def test_manifest_mismatch_is_refused(tmp_path):
    small_collect(tmp_path, num_episodes=2, max_steps=4)
    for change, key in [(dict(seed=8), "seed"), (dict(policy="behaviour"), "policy"),
                        (dict(env_params={"speed": 5.0}), "env_params"),
                        (dict(num_episodes=3), "num_episodes")]:
        kwargs = {"num_episodes": 2, "max_steps": 4, **change}
        with pytest.raises(DatasetError, match=key):
            small_collect(tmp_path, **kwargs)
    assert small_collect(tmp_path, num_episodes=2, max_steps=4)["complete"]


class TinyPixels(gym.Env):
    """A 40 x 60 RGB game: a bright square moves right; ends after 5 steps."""

    metadata = {"render_modes": []}
    observation_space = gym.spaces.Box(0, 255, (40, 60, 3), np.uint8)
    action_space = gym.spaces.Box(0.0, 1.0, (3,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self._frame(), {}

    def step(self, action):
        self.t += 1
        return self._frame(), float(action[0] > 0.5), self.t >= 5, False, {}

    def _frame(self):
        f = np.zeros((40, 60, 3), np.uint8)
        f[10:20, 10 + 4 * self.t: 20 + 4 * self.t, 1] = 255
        return f


def test_record_gym_with_preprocess_options(tmp_path):
    def policy(obs, rng):
        return rng.uniform(size=3)

    kwargs = dict(crop=(0, 10, 40, 40), out_size=(20, 20))
    manifest = record_gym(TinyPixels(), tmp_path, 4, policy, preprocess_kwargs=kwargs, seed=1)
    assert manifest["complete"] and manifest["config"]["preprocess"]["out_size"] == [20, 20]
    ep = EpisodeDataset(tmp_path, "all")[0]
    assert ep.frames.shape == (6, 20, 20) and ep.frames.dtype == np.uint8
    assert ep.frames[0, 5:10, 0:5].max() == 255 and ep.frames[0, 5:10, 5:].max() == 0
    np.testing.assert_array_equal(ep.rewards, np.r_[0.0, (ep.actions[:-1, 0] > 0.5)].astype(np.float32))
    assert record_gym(TinyPixels(), tmp_path, 4, policy, preprocess_kwargs=kwargs, seed=1)["complete"]
    with pytest.raises(DatasetError, match="seed"):
        record_gym(TinyPixels(), tmp_path, 4, policy, preprocess_kwargs=kwargs, seed=2)
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".tmp-")]


def test_atomic_write_replaces_whole_or_not_at_all_with_the_asked_permissions(tmp_path):
    path = tmp_path / "results.json"
    atomic_write_text(path, "old ✓\n")
    assert path.read_bytes() == "old ✓\n".encode()
    umask = os.umask(0o022)
    try:
        atomic_write_text(path, "new\n")
        assert path.stat().st_mode & 0o777 == 0o644  # as open() would: 0o666 less the umask
        atomic_write(path, lambda f: f.write(b"private"), mode=0o600)
        assert path.read_bytes() == b"private" and path.stat().st_mode & 0o777 == 0o600
        os.umask(0o077)
        atomic_write(path, lambda f: f.write(b"figure"), mode=0o644)  # exactly the mode, whatever the umask
        assert path.stat().st_mode & 0o777 == 0o644
    finally:
        os.umask(umask)

    def fails_halfway(f):
        f.write(b"half")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space left"):
        atomic_write(path, fails_halfway)
    assert path.read_bytes() == b"figure" and sorted(os.listdir(tmp_path)) == ["results.json"]
    # Episode files and manifests: whole files, readable by their owner only (as ever).
    small_collect(tmp_path / "data", num_episodes=2, max_steps=4)
    files = [p for p in (tmp_path / "data").iterdir() if p.name != LOCK_NAME]
    assert files and {p.stat().st_mode & 0o777 for p in files} == {0o600}


def test_collect_with_a_max_filter_stores_the_filtered_frames_shrunk(tmp_path):
    """`collect(obs_size=16, max_filter=3)`: every stored frame is the game's 150 x 150 frame
    (the same episode replayed step by step) under scipy's 3 x 3 maximum filter, then area-shrunk
    to 16 x 16; the manifest says so, and without the option it says nothing of it."""
    from scipy.ndimage import maximum_filter

    manifest = small_collect(tmp_path / "max", num_episodes=2, obs_size=16, max_filter=3)
    assert manifest["config"]["max_filter"] == 3 and manifest["config"]["obs_size"] == 16
    assert "max_filter" not in small_collect(tmp_path / "plain", num_episodes=1, obs_size=16)["config"]
    game = game_for()
    params = game.default_params.replace(max_steps=np.int32(12))
    ep = EpisodeDataset(tmp_path / "max", "all")[1]
    frames, _, _ = _replay(game, params, 7, 1)
    filtered = maximum_filter(frames.astype(np.float32) / 255.0, size=(1, 3, 3), mode="nearest")
    expected = np.asarray(jax.image.resize(filtered, (len(frames), 16, 16), "linear", antialias=True))
    np.testing.assert_allclose(ep.frames.astype(np.float32), np.round(expected * 255.0), atol=1.0)
    plain = np.asarray(jax.image.resize(frames.astype(np.float32) / 255.0, (len(frames), 16, 16), "linear",
                                        antialias=True))
    assert np.mean(np.abs(ep.frames / 255.0 - plain)) > 0.01  # the filter changed what was stored
