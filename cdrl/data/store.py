"""On-disk episode data sets: the episode type, collection, recording and loading.

Layout of a data set directory::

    manifest.json            what was collected and how, the episode list, the split
    episode_000000.npz       one file per episode: frames, actions, rewards
    episode_000001.npz
    ...

Each episode file holds ``frames`` [N, H, W] uint8 (pre-processed observations times
255), ``actions`` [N, A] float32 in [0, 1] and ``rewards`` [N] float32 (see
:class:`Episode`).  Every file, the manifest included, is written atomically: to a
temporary file in the same directory (name starting with ``.tmp-``), flushed and
fsync-ed, then renamed over the final name.  An interrupted collection therefore
leaves only whole episodes (plus possibly a ``.tmp-`` file, which readers ignore and
the next collection removes); running :func:`collect` again on the same directory
resumes it, skipping the episodes already present.  A collection holds the directory's
lock (:mod:`cdrl.data.lock`) while it writes, so a second one is refused with the first's
pid; reading a complete data set takes no lock.

The split is by episode: ``round(test_fraction * num_episodes)`` episodes, chosen by a
permutation seeded from the collection seed, are the test split; the rest train.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import tempfile
import zipfile
import zlib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from cdrl.data.episode import Episode  # noqa: F401  (re-exported: the unit a data set stores)
from cdrl.data.lock import DirLock

MANIFEST_NAME = "manifest.json"
FORMAT_NAME = "cdrl-episodes"
FORMAT_VERSION = 1
TEMP_PREFIX = ".tmp-"


class DatasetError(ValueError):
    """A data set directory or episode file is unusable (the message names it)."""


def episode_filename(index: int) -> str:
    """File name of episode ``index`` inside a data set directory."""
    return f"episode_{index:06d}.npz"


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write(path: str | os.PathLike, write: Callable[[Any], None]) -> None:
    """Writes ``path`` atomically: ``write(file)`` fills a temporary file in the same
    directory, which is flushed, fsync-ed and renamed over ``path``.  On any error
    the temporary file is removed and ``path`` is left as it was."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f"{TEMP_PREFIX}{path.name}.")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    _fsync_dir(path.parent)


def _write_npz(f, episode: Episode, compress: bool) -> None:
    """Writes an ``.npz`` (a zip of ``.npy`` files, readable by ``np.load``); with
    ``compress``, deflate level 1 (several times faster than numpy's default level
    and about as small on these images)."""
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(f, "w", compression=method, compresslevel=1 if compress else None) as z:
        for name in ("frames", "actions", "rewards"):
            with z.open(f"{name}.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, getattr(episode, name), allow_pickle=False)


class DatasetWriteError(DatasetError):
    """An episode file or manifest could not be written (e.g. the disk is full); the file
    it would have replaced, and every other file, is as it was."""


def save_episode(path: str | os.PathLike, episode: Episode, compress: bool = True) -> None:
    """Writes one episode as an ``.npz`` file, atomically; a failed write raises
    :class:`DatasetWriteError` naming the file and leaves nothing behind."""
    try:
        atomic_write(path, lambda f: _write_npz(f, episode, compress))
    except OSError as e:
        raise DatasetWriteError(
            f"could not write episode file {path}: {e.strerror or e}; the episodes written before it are "
            "intact, and running the same collection again resumes it") from e


def load_episode(path: str | os.PathLike) -> Episode:
    """Reads one episode file; a missing, truncated or malformed file raises
    :class:`DatasetError` naming it."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = {"frames", "actions", "rewards"} - set(data.files)
            if missing:
                raise DatasetError(f"episode file {path} lacks arrays {sorted(missing)}")
            arrays = {k: data[k] for k in ("frames", "actions", "rewards")}
    except DatasetError:
        raise
    except FileNotFoundError:
        raise DatasetError(f"episode file {path} is missing") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as e:
        raise DatasetError(f"episode file {path} is truncated or corrupt: {e}") from e
    try:
        return Episode(**arrays)
    except ValueError as e:
        raise DatasetError(f"episode file {path} is invalid: {e}") from e


def split_episodes(num_episodes: int, test_fraction: float, seed: int) -> dict[str, list[int]]:
    """The train/test split by episode index, deterministic from ``seed``."""
    if not 0.0 <= test_fraction < 1.0:
        raise ValueError(f"test_fraction must be in [0, 1), got {test_fraction}")
    order = np.random.default_rng([int(seed), 0x5EED]).permutation(num_episodes)
    n_test = int(round(test_fraction * num_episodes))
    test = sorted(int(i) for i in order[:n_test])
    train = sorted(int(i) for i in order[n_test:])
    return {"train": train, "test": test}


def _read_manifest(out_dir: Path) -> dict | None:
    path = out_dir / MANIFEST_NAME
    if not path.exists():
        return None
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise DatasetError(f"manifest {path} is unreadable: {e}") from e
    if manifest.get("format") != FORMAT_NAME:
        raise DatasetError(f"{path} is not a {FORMAT_NAME} manifest")
    return manifest


def _write_manifest(out_dir: Path, manifest: dict) -> None:
    text = json.dumps(manifest, indent=1, sort_keys=True).encode()
    try:
        atomic_write(out_dir / MANIFEST_NAME, lambda f: f.write(text))
    except OSError as e:
        raise DatasetWriteError(f"could not write {out_dir / MANIFEST_NAME}: {e.strerror or e}; "
                                "the previous manifest is intact") from e


class _Writer:
    """Creates or resumes a data set directory for one collection ``config``, holding the
    directory's lock until :meth:`close` (use it as a context manager)."""

    def __init__(self, out_dir: str | os.PathLike, config: dict):
        self.dir = Path(out_dir)
        self.lock = DirLock(self.dir, "data set").acquire()
        try:
            self._open(config)
        except BaseException:
            self.lock.release()
            raise

    def __enter__(self) -> "_Writer":
        return self

    def __exit__(self, *exc) -> None:
        self.lock.release()

    def _open(self, config: dict) -> None:
        self.config = json.loads(json.dumps(config))
        existing = _read_manifest(self.dir)
        known: dict[int, int] = {}
        if existing is not None:
            self._check_same(existing.get("config", {}))
            known = {int(e["index"]): int(e["length"]) for e in existing.get("episodes", [])}
        for leftover in self.dir.glob(f"{TEMP_PREFIX}*"):
            leftover.unlink(missing_ok=True)
        n = int(config["num_episodes"])
        self.lengths: dict[int, int] = {}
        for i in range(n):
            path = self.dir / episode_filename(i)
            if not path.exists():
                continue
            self.lengths[i] = known[i] if i in known else len(load_episode(path))
        self.split = split_episodes(n, float(config["test_fraction"]), int(config["seed"]))
        self.meta: dict[str, Any] = dict(existing.get("data", {})) if existing else {}
        self._save_manifest()

    def _check_same(self, old: dict) -> None:
        diffs = _config_diffs(old, self.config)
        if diffs:
            raise DatasetError(
                f"{self.dir / MANIFEST_NAME} was written by a different collection; "
                "use a new directory or the same settings.  Differences: " + "; ".join(diffs)
            )

    @property
    def missing(self) -> list[int]:
        """Indices of the episodes still to write."""
        return [i for i in range(int(self.config["num_episodes"])) if i not in self.lengths]

    def write(self, index: int, episode: Episode, compress: bool = True) -> None:
        save_episode(self.dir / episode_filename(index), episode, compress)
        self.lengths[index] = len(episode)
        self.meta = {
            "frame_shape": list(episode.frames.shape[1:]),
            "frame_dtype": str(episode.frames.dtype),
            "action_dim": int(episode.actions.shape[1]),
        }

    def _save_manifest(self) -> None:
        n = int(self.config["num_episodes"])
        manifest = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "config": self.config,
            "data": self.meta,
            "episodes": [
                {"index": i, "file": episode_filename(i), "length": self.lengths[i]}
                for i in sorted(self.lengths)
            ],
            "split": self.split,
            "complete": len(self.lengths) == n,
        }
        _write_manifest(self.dir, manifest)

    def flush(self) -> None:
        """Rewrites the manifest to list every episode written so far."""
        self._save_manifest()


def _config_diffs(old: dict, new: dict) -> list[str]:
    """How collection config ``new`` differs from the ``old`` one of an existing data set."""
    if "env_params" in old and "env_params" in new:
        # A game parameter added after the data set was collected had its default value; one
        # the game no longer has (a removed test-only reward) is not compared.
        from envs.slither import SlitherParams

        defaults = _params_dict(SlitherParams())
        kept = {k: v for k, v in old["env_params"].items() if k in defaults}
        old = {**old, "env_params": {**defaults, **kept}}
    return [
        f"{key}: existing {old.get(key)!r} != requested {new.get(key)!r}"
        for key in sorted(set(old) | set(new))
        if old.get(key) != new.get(key)
    ]


def _finished(out_dir: Path, config: dict) -> dict | None:
    """The manifest of ``out_dir`` if it holds a complete data set of ``config`` (checked
    without the lock and without writing anything, so readers can use it)."""
    manifest = _read_manifest(out_dir) if (out_dir / MANIFEST_NAME).exists() else None
    if manifest is None or not manifest.get("complete"):
        return None
    if _config_diffs(manifest.get("config", {}), json.loads(json.dumps(config))):
        return None
    return manifest


def _write_set(out_dir, config: dict, fill) -> dict:
    """The manifest of the data set `config` in `out_dir`: read back if it is complete, else
    `fill(writer)` records the missing episodes under the directory's lock first."""
    done = _finished(Path(out_dir), config)
    if done is not None:
        return done
    with _Writer(out_dir, config) as writer:
        fill(writer)
        return _read_manifest(writer.dir)


def _params_dict(params) -> dict[str, float | int]:
    """Field name -> Python number (a float32 value as its shortest decimal form)."""
    out = {}
    for field in dataclasses.fields(params):
        value = np.asarray(getattr(params, field.name))
        if np.issubdtype(value.dtype, np.floating):
            out[field.name] = float(str(np.float32(value)))
        else:
            out[field.name] = int(value)
    return out


@functools.lru_cache(maxsize=8)
def _rollout_fn(game_items: tuple, policy_name: str, chunk_steps: int, obs_size: int = 150):
    """A jitted function running a batch of episodes for ``chunk_steps`` steps.

    Carry per episode: (game state, policy state, obs of that state, reward on
    arriving at obs, finished = the episode ended before obs, key).  Each step emits
    (uint8 frame, action, reward, valid = not finished) for the current
    observation, then steps the game.
    """
    import jax
    import jax.numpy as jnp

    from cdrl.data.frames import resize_obs
    from envs import fastrng
    from envs.policies import get_policy
    from envs.slither import Slither

    game = Slither(**dict(game_items))
    policy = get_policy(policy_name)

    def start(key, params):
        k_reset, k_policy, k_run = fastrng.split(key, 3)
        state = game.reset_state(k_reset, params)
        obs = game.get_obs(state, params)
        return (state, policy.init(k_policy), obs, jnp.zeros((), jnp.float32),
                jnp.zeros((), bool), k_run)

    def one_step(carry, params):
        state, pstate, obs, reward, finished, key = carry
        key, k_policy, k_env = fastrng.split(key, 3)
        action, pstate = policy.step(k_policy, pstate, obs)
        frame = jnp.round(resize_obs(obs, obs_size) * 255.0).astype(jnp.uint8)
        out = (frame, action.astype(jnp.float32), reward, ~finished)
        is_last = state.terminated | (state.time >= params.max_steps)
        state, reward, _, _, _ = game.step_state(k_env, state, action, params)
        obs = game.get_obs(state, params)
        carry = (state, pstate, obs, reward.astype(jnp.float32), finished | is_last, key)
        return carry, out

    def run(carry, params):
        def body(c, _):
            return jax.vmap(one_step, in_axes=(0, None))(c, params)

        return jax.lax.scan(body, carry, None, length=chunk_steps)

    return jax.jit(jax.vmap(start, in_axes=(0, None))), jax.jit(run)


def collect(
    out_dir: str | os.PathLike,
    num_episodes: int,
    policy: str = "behaviour",
    seed: int = 0,
    env_params=None,
    max_steps: int = 1000,
    test_fraction: float = 0.1,
    batch_size: int = 16,
    chunk_steps: int = 64,
    game_kwargs: dict | None = None,
    compress: bool = True,
    progress: bool | None = None,
    obs_size: int = 150,
) -> dict:
    """Collects ``num_episodes`` Slither episodes into ``out_dir`` (or resumes).

    Episodes run ``batch_size`` at a time as one vmapped game scanned over
    ``chunk_steps`` steps per call; a batch is written to disk (in a background
    thread, one episode after another) while the next one is simulated, and the
    manifest is rewritten after every written batch.  Episode ``i`` depends only on ``seed`` and ``i``
    (its key is ``envs.fastrng.fold_in(PRNGKey(seed), i)``), so resuming reproduces the same
    episodes.  An episode ends when the player dies or after ``max_steps`` steps
    (so it has at most ``max_steps + 1`` frames).

    Args:
      out_dir: data set directory (created if needed).
      num_episodes: number of episodes the data set should hold.
      policy: "behaviour" (behaviour switching) or "uniform" (uniform random).
      seed: collection seed (episode keys and the train/test split).
      env_params: :class:`envs.slither.SlitherParams`, or a dict of field overrides,
        or None for the defaults; ``max_steps`` overrides its ``max_steps``.
      max_steps: truncation length in steps.
      test_fraction: share of episodes held out as the test split.
      batch_size: episodes simulated together.
      chunk_steps: steps per compiled call (bounds device memory).
      game_kwargs: static sizes for :class:`envs.slither.Slither`.
      compress: write compressed ``.npz`` files.
      progress: show a tqdm bar (None = only on a terminal).
      obs_size: side of the stored observations; the game's 150 x 150 observation is
        area-resized to it (for the smaller architecture presets).
    Returns:
      The manifest (as written to ``out_dir/manifest.json``).
    Raises:
      DatasetError: the directory holds a data set collected with other settings, or
        an episode file in it is corrupt, or one could not be written (a full disk).
      LockedError: another process is writing to the directory.
    """
    from envs.policies import get_policy
    from envs.slither import SlitherParams, canonical_params

    get_policy(policy)
    if isinstance(env_params, dict):
        params = SlitherParams(**env_params)
    else:
        params = SlitherParams() if env_params is None else env_params
    params = canonical_params(params.replace(max_steps=int(max_steps)))
    game_kwargs = dict(sorted((game_kwargs or {}).items()))
    config = {
        "source": "slither",
        "policy": policy,
        "seed": int(seed),
        "env_params": _params_dict(params),
        "game": game_kwargs,
        "max_steps": int(max_steps),
        "test_fraction": float(test_fraction),
        "num_episodes": int(num_episodes),
        "obs_size": int(obs_size),
    }
    def fill(writer):
        if writer.missing:
            _simulate(writer, params, game_kwargs, policy, int(seed), int(max_steps), int(batch_size),
                      int(chunk_steps), int(obs_size), compress, progress)

    return _write_set(out_dir, config, fill)


def _simulate(writer: _Writer, params, game_kwargs: dict, policy: str, seed: int, max_steps: int, batch_size: int,
              chunk_steps: int, obs_size: int, compress: bool, progress: bool | None) -> None:
    """Runs and writes the episodes ``writer`` is missing (the body of :func:`collect`)."""
    import jax
    from tqdm.auto import tqdm

    from envs import fastrng

    missing = writer.missing
    start, run = _rollout_fn(tuple(game_kwargs.items()), policy, int(chunk_steps), int(obs_size))
    base = jax.random.PRNGKey(int(seed))
    episode_keys = jax.jit(jax.vmap(lambda i: fastrng.fold_in(base, i)))
    bar = tqdm(total=len(missing), desc="collect", unit="ep", disable=None if progress is None else not progress)

    def write_batch(episodes):
        for index, episode in episodes:
            writer.write(index, episode, compress)
            bar.update(1)

    pending = None
    with ThreadPoolExecutor(max_workers=1) as pool:
        for b in range(0, len(missing), batch_size):
            batch = missing[b:b + batch_size]
            padded = batch + [batch[-1]] * (batch_size - len(batch))
            carry = start(episode_keys(np.asarray(padded, np.uint32)), params)
            pieces = []
            steps = 0
            while steps <= max_steps:
                carry, out = run(carry, params)
                out = jax.device_get(out)
                pieces.append(out)
                steps += chunk_steps
                if not out[3][-1].any():
                    break
            frames, actions, rewards, valid = (np.concatenate(p, axis=0) for p in zip(*pieces))
            episodes = []
            for j, index in enumerate(batch):
                n = int(valid[:, j].sum())
                episodes.append((index, Episode(
                    frames=np.ascontiguousarray(frames[:n, j]),
                    actions=np.ascontiguousarray(actions[:n, j]),
                    rewards=np.ascontiguousarray(rewards[:n, j]),
                )))
            if pending is not None:
                pending.result()
                writer.flush()
            pending = pool.submit(write_batch, episodes)
        pending.result()
        writer.flush()
    bar.close()


def save_dataset(out_dir: str | os.PathLike, episodes: Sequence[Episode], source: str = "episodes",
                 seed: int = 0, test_fraction: float = 0.1, compress: bool = True) -> dict:
    """Writes ``episodes`` (recorded elsewhere) as a data set directory, split by ``seed``
    like a collection; returns the manifest.  Resumes like :func:`collect`."""
    config = {"source": str(source), "seed": int(seed), "test_fraction": float(test_fraction),
              "num_episodes": len(episodes)}
    with _Writer(out_dir, config) as writer:
        for index in writer.missing:
            writer.write(index, episodes[index], compress)
        writer.flush()
        return _read_manifest(writer.dir)


def record_gym(
    env,
    out_dir: str | os.PathLike,
    num_episodes: int,
    policy_fn: Callable[[np.ndarray, np.random.Generator], np.ndarray],
    preprocess_kwargs: dict | None = None,
    seed: int = 0,
    max_steps: int | None = None,
    test_fraction: float = 0.1,
    action_fn: Callable[[np.ndarray], Any] | None = None,
    compress: bool = True,
    config_extra: dict | None = None,
) -> dict:
    """Records episodes of any gymnasium environment with image observations.

    Observations ([H, W, C] or [H, W] images, uint8 or float in [0, 1]) are
    pre-processed with :func:`envs.preprocess.preprocess` (``preprocess_kwargs``:
    ``crop`` and ``out_size``; the defaults suit a 500 x 300 frame) and stored as
    uint8.  Writing, resuming and the manifest work as in :func:`collect`.

    Args:
      env: a gymnasium environment.
      out_dir: data set directory.
      num_episodes: number of episodes.
      policy_fn: ``policy_fn(raw_obs, rng) -> action``: a 1-D array of values in
        [0, 1], which is what gets recorded.
      preprocess_kwargs: options for :func:`envs.preprocess.preprocess`.
      seed: episode ``i`` resets the environment with ``seed + i`` and gives the
        policy ``np.random.default_rng([seed, i])``.
      max_steps: stop an episode after this many steps (None = until the
        environment ends it).
      test_fraction: share of episodes held out as the test split.
      action_fn: maps the recorded action to what ``env.step`` takes (default:
        the action itself).
      compress: write compressed ``.npz`` files.
      config_extra: more of what defines the recording (the environment's options,
        the observation mode), stored in the manifest's config and checked on resume.
    Returns:
      The manifest.
    """
    kwargs = dict(preprocess_kwargs or {})
    spec = getattr(env, "spec", None)
    config = {
        "source": "gym",
        "env": spec.id if spec is not None else type(env.unwrapped).__name__,
        "policy": getattr(policy_fn, "__name__", type(policy_fn).__name__),
        "seed": int(seed),
        "preprocess": {k: list(v) if isinstance(v, tuple) else v for k, v in kwargs.items()},
        "max_steps": None if max_steps is None else int(max_steps),
        "test_fraction": float(test_fraction),
        "num_episodes": int(num_episodes),
        **(config_extra or {}),
    }
    return _write_set(out_dir, config,
                      lambda writer: _record(writer, env, policy_fn, kwargs, int(seed), max_steps, action_fn, compress))


def _record(writer: _Writer, env, policy_fn, kwargs: dict, seed: int, max_steps: int | None, action_fn,
            compress: bool) -> None:
    """Plays and writes the episodes ``writer`` is missing (the body of :func:`record_gym`)."""
    from envs.preprocess import preprocess

    def to_frame(obs) -> np.ndarray:
        obs = np.asarray(obs)
        if obs.ndim == 2:
            obs = obs[..., None]
        return np.round(preprocess(obs, **kwargs) * 255.0).astype(np.uint8)

    for index in writer.missing:
        rng = np.random.default_rng([int(seed), index])
        obs, _ = env.reset(seed=int(seed) + index)
        frames, actions, rewards = [], [], [0.0]
        steps = 0
        while True:
            action = np.asarray(policy_fn(obs, rng), np.float32).reshape(-1)
            frames.append(to_frame(obs))
            actions.append(action)
            if max_steps is not None and steps >= max_steps:
                break
            obs, reward, terminated, truncated, _ = env.step(
                action if action_fn is None else action_fn(action)
            )
            steps += 1
            if terminated or truncated:
                frames.append(to_frame(obs))
                actions.append(np.asarray(policy_fn(obs, rng), np.float32).reshape(-1))
                rewards.append(float(reward))
                break
            rewards.append(float(reward))
        episode = Episode(
            frames=np.stack(frames),
            actions=np.stack(actions).astype(np.float32),
            rewards=np.asarray(rewards[:len(frames)], np.float32),
        )
        writer.write(index, episode, compress)
        writer.flush()


class EpisodeDataset:
    """Read access to a data set directory, one episode file at a time.

    Only the manifest is read up front; ``dataset[i]`` loads episode ``i`` of the
    split from disk when asked, so data sets larger than memory stream.

    Args:
      path: the data set directory.
      split: "train", "test" or "all".
    """

    def __init__(self, path: str | os.PathLike, split: str = "train"):
        if split not in ("train", "test", "all"):
            raise ValueError(f"split must be 'train', 'test' or 'all', got {split!r}")
        self.path = Path(path)
        manifest = _read_manifest(self.path)
        if manifest is None:
            raise DatasetError(f"{self.path} has no {MANIFEST_NAME}")
        self.manifest = manifest
        self.split = split
        present = {int(e["index"]): e for e in manifest["episodes"]}
        wanted = sorted(present) if split == "all" else manifest["split"][split]
        self._entries = [present[i] for i in wanted if i in present]

    def __len__(self) -> int:
        return len(self._entries)

    def __getitem__(self, i: int) -> Episode:
        if not -len(self) <= i < len(self):
            raise IndexError(f"episode {i} out of range for {len(self)} episodes")
        entry = self._entries[i]
        path = self.path / entry["file"]
        episode = load_episode(path)
        if len(episode) != int(entry["length"]):
            raise DatasetError(
                f"episode file {path} has {len(episode)} frames, manifest says {entry['length']}"
            )
        return episode

    def __iter__(self) -> Iterator[Episode]:
        for i in range(len(self)):
            yield self[i]

    @property
    def indices(self) -> list[int]:
        """Episode indices (as in the file names) of this split, in order."""
        return [int(e["index"]) for e in self._entries]

    @property
    def lengths(self) -> list[int]:
        """Number of frames of each episode of this split."""
        return [int(e["length"]) for e in self._entries]

    @property
    def num_frames(self) -> int:
        """Total number of frames in this split."""
        return sum(self.lengths)

    @property
    def complete(self) -> bool:
        """Whether the collection that wrote the directory finished."""
        return bool(self.manifest.get("complete", False))

    def verify(self, workers: int | None = None) -> None:
        """Checks every episode file of the split without building episodes: each is a
        readable zip whose members pass their CRC check (a truncated or corrupted file
        fails), holds ``frames`` [N, H, W], ``actions`` [N, A] float32 in [0, 1] and
        ``rewards`` [N] float32 (finite), with N, (H, W), the frame dtype and A as the
        manifest says.  Files are checked in ``workers`` threads (default: up to 8).
        Raises :class:`DatasetError` naming the first bad file."""
        data = self.manifest.get("data", {})
        expect = {
            "frame_shape": tuple(data["frame_shape"]) if "frame_shape" in data else None,
            "frame_dtype": data.get("frame_dtype"),
            "action_dim": data.get("action_dim"),
        }
        jobs = [(self.path / e["file"], int(e["length"])) for e in self._entries]
        if not jobs:
            return
        with ThreadPoolExecutor(max_workers=workers or min(8, len(jobs), os.cpu_count() or 1)) as pool:
            for error in pool.map(lambda job: _check_episode_file(*job, **expect), jobs):
                if error is not None:
                    raise DatasetError(error)


_READ_BLOCK = 1 << 22


def _npy_header(member) -> tuple[tuple[int, ...], np.dtype]:
    version = np.lib.format.read_magic(member)
    read = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
    if version not in read:
        raise ValueError(f"unsupported .npy version {version}")
    shape, fortran, dtype = read[version](member)
    if fortran:
        raise ValueError("Fortran-ordered arrays are not written by cdrl")
    return shape, dtype


def _check_episode_file(path: Path, length: int, frame_shape: tuple | None, frame_dtype: str | None,
                        action_dim: int | None) -> str | None:
    """What is wrong with episode file ``path`` (None: nothing); see :meth:`EpisodeDataset.verify`."""
    try:
        with zipfile.ZipFile(path) as z:
            names = set(z.namelist())
            missing = {"frames.npy", "actions.npy", "rewards.npy"} - names
            if missing:
                return f"episode file {path} lacks arrays {sorted(m[:-4] for m in missing)}"
            with z.open("frames.npy") as member:
                shape, dtype = _npy_header(member)
                while member.read(_READ_BLOCK):  # decompress all of it: the CRC is checked at the end
                    pass
            arrays = {}
            for name in ("actions", "rewards"):
                with z.open(f"{name}.npy") as member:
                    arrays[name] = np.lib.format.read_array(member, allow_pickle=False)
    except FileNotFoundError:
        return f"episode file {path} is missing"
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError, zlib.error) as e:
        return f"episode file {path} is truncated or corrupt: {e}"
    actions, rewards = arrays["actions"], arrays["rewards"]
    problems = []
    if len(shape) != 3 or shape[0] != length:
        problems.append(f"frames have shape {shape}, the manifest says {length} frames")
    elif frame_shape is not None and tuple(shape[1:]) != frame_shape:
        problems.append(f"frames are {shape[1]}x{shape[2]}, the manifest says {frame_shape[0]}x{frame_shape[1]}")
    if frame_dtype is not None and str(dtype) != frame_dtype:
        problems.append(f"frames are {dtype}, the manifest says {frame_dtype}")
    elif str(dtype) not in ("uint8", "float32"):
        problems.append(f"frames are {dtype}, not uint8 or float32")
    if actions.dtype != np.float32 or actions.ndim != 2 or actions.shape[0] != length:
        problems.append(f"actions are {actions.dtype} {actions.shape}, expected float32 [{length}, A]")
    elif action_dim is not None and actions.shape[1] != action_dim:
        problems.append(f"actions have {actions.shape[1]} values, the manifest says {action_dim}")
    elif not (np.all(np.isfinite(actions)) and actions.min(initial=0.0) >= 0.0 and actions.max(initial=0.0) <= 1.0):
        problems.append("actions are not finite values in [0, 1]")
    if rewards.dtype != np.float32 or rewards.shape != (length,):
        problems.append(f"rewards are {rewards.dtype} {rewards.shape}, expected float32 [{length}]")
    elif not np.all(np.isfinite(rewards)):
        problems.append("rewards are not finite")
    if str(dtype) == "float32" and not problems:
        try:
            Episode(**dict(np.load(path, allow_pickle=False)))  # float frames: check their range too
        except ValueError as e:
            problems.append(str(e))
    return f"episode file {path} is invalid: " + "; ".join(problems) if problems else None
