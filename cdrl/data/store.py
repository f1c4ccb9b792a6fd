"""On-disk episode data sets: the format of a data set directory, and reading one.

Layout of a data set directory::

    manifest.json            what was collected and how, the episode list, the split
    episode_000000.npz       one file per episode: frames, actions, rewards
    episode_000001.npz
    ...

Each episode file holds ``frames`` [N, H, W] uint8 (pre-processed observations times
255), ``actions`` [N, A] float32 in [0, 1] and ``rewards`` [N] float32 (see
:class:`Episode`).  Every file, the manifest included, is written atomically
(:mod:`cdrl.data.atomic`): to a temporary file in the same directory (name starting with
``.tmp-``), flushed and fsync-ed, then renamed over the final name.  An interrupted
collection therefore leaves only whole episodes (plus possibly a ``.tmp-`` file, which
readers ignore and the next collection removes).

Data sets are written by :mod:`cdrl.data.writer` (resumable, under the directory's lock:
:mod:`cdrl.data.lock`), which :func:`cdrl.data.collect.collect` (the built-in game) and
:func:`cdrl.data.gymrec.record_gym` (any gymnasium game) use; reading a complete data set
(:class:`EpisodeDataset`) takes no lock.

The split is by episode: ``round(test_fraction * num_episodes)`` episodes, chosen by a
permutation seeded from the collection seed, are the test split; the rest train.
"""

from __future__ import annotations

import json
import os
import threading
import zipfile
import zlib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Iterator

import numpy as np

from cdrl.data.atomic import atomic_write
from cdrl.data.episode import Episode  # noqa: F401  (re-exported: the unit a data set stores)

MANIFEST_NAME = "manifest.json"
FORMAT_NAME = "cdrl-episodes"
FORMAT_VERSION = 1
# The permission bits of every file of a data set (episode files, the manifest).
FILE_MODE = 0o600


class DatasetError(ValueError):
    """A data set directory or episode file is unusable (the message names it)."""


def episode_filename(index: int) -> str:
    """File name of episode ``index`` inside a data set directory."""
    return f"episode_{index:06d}.npz"


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
        atomic_write(path, lambda f: _write_npz(f, episode, compress), FILE_MODE)
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


def read_manifest(out_dir: Path) -> dict | None:
    """The manifest of data set directory ``out_dir`` (None: it has none); :class:`DatasetError`
    if it is unreadable or not a data set's."""
    path = out_dir / MANIFEST_NAME
    if not path.exists():
        return None
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise DatasetError(f"manifest {path} is unreadable: {e}") from e
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT_NAME:
        raise DatasetError(f"{path} is not a {FORMAT_NAME} manifest")
    _check_entries(out_dir, manifest)
    return manifest


def _check_entries(out_dir: Path, manifest: dict) -> None:
    """Refuse a manifest whose episode list is malformed or names a file outside ``out_dir``:
    an absolute path, a ``..`` part, or a symbolic link leading out of the directory. A data
    set is a directory, and nothing outside it is read."""
    path = out_dir / MANIFEST_NAME
    entries, split = manifest.get("episodes"), manifest.get("split")
    if not isinstance(entries, list) or not isinstance(split, dict):
        raise DatasetError(f"manifest {path} has no episode list and split")
    root = out_dir.resolve()
    for entry in entries:
        if not (isinstance(entry, dict) and isinstance(entry.get("index"), int) and isinstance(entry.get("file"), str)
                and isinstance(entry.get("length"), int) and entry["length"] >= 0):
            raise DatasetError(f"manifest {path}: episode entry {entry!r} is not an index, a file name and a length")
        name = entry["file"]
        relative = Path(name)
        if relative.is_absolute() or ".." in relative.parts or not name or not (root / relative).resolve().is_relative_to(root):
            raise DatasetError(f"manifest {path}: episode {entry['index']}'s file {name!r} is outside the data set "
                               f"directory {out_dir}; a data set reads only files inside its directory")
    for name in ("train", "test"):
        if not (isinstance(split.get(name), list) and all(isinstance(i, int) for i in split[name])):
            raise DatasetError(f"manifest {path}: its {name} split is not a list of episode indices")



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
        manifest = read_manifest(self.path)
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
    def files(self) -> list[str]:
        """Episode file names (inside the data set directory) of this split, in order."""
        return [e["file"] for e in self._entries]

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
# numpy parses a .npy header with `ast.literal_eval`, and CPython 3.11's parser is not safe to
# run from two threads at once (it can raise `SystemError: AST constructor recursion depth
# mismatch`): the checking threads read their headers (and the small arrays they check whole)
# one at a time.
_HEADER_PARSE = threading.Lock()


def _npy_header(member) -> tuple[tuple[int, ...], np.dtype]:
    version = np.lib.format.read_magic(member)
    read = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
    if version not in read:
        raise ValueError(f"unsupported .npy version {version}")
    with _HEADER_PARSE:
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
                with z.open(f"{name}.npy") as member, _HEADER_PARSE:
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
            with _HEADER_PARSE:
                stored = dict(np.load(path, allow_pickle=False))
            Episode(**stored)  # float frames: check their range too
        except ValueError as e:
            problems.append(str(e))
    return f"episode file {path} is invalid: " + "; ".join(problems) if problems else None
