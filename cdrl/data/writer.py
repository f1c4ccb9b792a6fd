"""Writing a data set directory (the format: :mod:`cdrl.data.store`): resumable, one whole
episode file at a time, under the directory's lock.

A :class:`Writer` opens a directory for one collection's ``config``: it refuses a directory
holding a data set of other settings, removes the ``.tmp-`` files of an interrupted write,
finds the episodes already present, and rewrites the manifest when asked
(:meth:`Writer.flush`), listing every episode written so far.  Running the same collection
again on the same directory therefore resumes it, skipping the episodes already present.
A writer holds the directory's lock (:mod:`cdrl.data.lock`) while it writes, so a second
one is refused with the first's pid.  :func:`write_set` returns a complete data set's
manifest without taking the lock, else fills in what is missing.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from cdrl.data.atomic import TEMP_PREFIX, atomic_write
from cdrl.data.episode import Episode
from cdrl.data.lock import DirLock
from cdrl.data.store import (FILE_MODE, FORMAT_NAME, FORMAT_VERSION, MANIFEST_NAME, DatasetError, DatasetWriteError,
                             episode_filename, load_episode, read_manifest, save_episode, split_episodes)


def _write_manifest(out_dir: Path, manifest: dict) -> None:
    text = json.dumps(manifest, indent=1, sort_keys=True).encode()
    try:
        atomic_write(out_dir / MANIFEST_NAME, lambda f: f.write(text), FILE_MODE)
    except OSError as e:
        raise DatasetWriteError(f"could not write {out_dir / MANIFEST_NAME}: {e.strerror or e}; "
                                "the previous manifest is intact") from e


class Writer:
    """Creates or resumes a data set directory for one collection ``config``, holding the
    directory's lock until it exits (use it as a context manager)."""

    def __init__(self, out_dir: str | os.PathLike, config: dict):
        self.dir = Path(out_dir)
        self.lock = DirLock(self.dir, "data set").acquire()
        try:
            self._open(config)
        except BaseException:
            self.lock.release()
            raise

    def __enter__(self) -> "Writer":
        return self

    def __exit__(self, *exc) -> None:
        self.lock.release()

    def _open(self, config: dict) -> None:
        self.config = json.loads(json.dumps(config))
        existing = read_manifest(self.dir)
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

        defaults = params_dict(SlitherParams())
        kept = {k: v for k, v in old["env_params"].items() if k in defaults}
        old = {**old, "env_params": {**defaults, **kept}}
    return [
        f"{key}: existing {old.get(key)!r} != requested {new.get(key)!r}"
        for key in sorted(set(old) | set(new))
        if old.get(key) != new.get(key)
    ]


def check_collection(num_episodes, max_steps, obs_size=None, seed=0, largest: int | None = None) -> None:
    """Refuse, before anything is written, numbers a collection cannot record: fewer than 1
    episode, an episode step limit below 1 (None: the game ends its episodes), a frame side
    below 1 (or above `largest`, the game's own frames; None: not chosen here), a negative seed. ValueError naming
    the option (as `cdrl collect` spells it)."""
    for option, value, low in (("--episodes", num_episodes, 1), ("--episode-steps", max_steps, 1),
                               ("--obs-size", obs_size, 1), ("--seed", seed, 0)):
        if value is None and option in ("--episode-steps", "--obs-size"):
            continue
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            raise ValueError(f"{option} must be an integer >= {low}, got {value!r}")
    if largest is not None and obs_size is not None and obs_size > largest:
        raise ValueError(f"--obs-size must be at most {largest}, the side of the game's frames; got {obs_size}")


def _finished(out_dir: Path, config: dict) -> dict | None:
    """The manifest of ``out_dir`` if it holds a complete data set of ``config`` (checked
    without the lock and without writing anything, so readers can use it)."""
    manifest = read_manifest(out_dir) if (out_dir / MANIFEST_NAME).exists() else None
    if manifest is None or not manifest.get("complete"):
        return None
    if _config_diffs(manifest.get("config", {}), json.loads(json.dumps(config))):
        return None
    return manifest


def write_set(out_dir, config: dict, fill) -> dict:
    """The manifest of the data set `config` in `out_dir`: read back if it is complete, else
    `fill(writer)` records the missing episodes under the directory's lock first."""
    done = _finished(Path(out_dir), config)
    if done is not None:
        return done
    with Writer(out_dir, config) as writer:
        fill(writer)
        return read_manifest(writer.dir)


def params_dict(params) -> dict[str, float | int]:
    """Field name -> Python number (a float32 value as its shortest decimal form)."""
    out = {}
    for field in dataclasses.fields(params):
        value = np.asarray(getattr(params, field.name))
        if np.issubdtype(value.dtype, np.floating):
            out[field.name] = float(str(np.float32(value)))
        else:
            out[field.name] = int(value)
    return out


def save_dataset(out_dir: str | os.PathLike, episodes: Sequence[Episode], source: str = "episodes",
                 seed: int = 0, test_fraction: float = 0.1, compress: bool = True) -> dict:
    """Writes ``episodes`` (recorded elsewhere) as a data set directory, split by ``seed``
    like a collection; returns the manifest.  Resumes like :func:`cdrl.data.collect.collect`."""
    config = {"source": str(source), "seed": int(seed), "test_fraction": float(test_fraction),
              "num_episodes": len(episodes)}
    with Writer(out_dir, config) as writer:
        for index in writer.missing:
            writer.write(index, episodes[index], compress)
        writer.flush()
        return read_manifest(writer.dir)
