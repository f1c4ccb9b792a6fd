"""The fingerprint of the episodes a run trains on, so that a resume notices data that changed.

A data set's fingerprint is the digest of its manifest and, per episode file of the split,
its size and the CRC-32 of each array in it as the zip stores them. Those CRCs need no
rehashing: reading them takes a file's directory only, and they are trustworthy because
`EpisodeDataset.verify`, which every run calls before step 1, inflates every array and checks
it against them. Two episode files swapped, one re-recorded or one removed all change the
fingerprint. Episodes held in memory (synthetic data) are fingerprinted by the CRC-32 of
their arrays.

`fingerprint(train, test)` is pure (it reads the files, writes nothing); `changes(old, new)`
says what differs, in words. The run directory keeps a run's fingerprint (`RunDir.check_data`).
"""
from __future__ import annotations

import hashlib
import json
import zipfile
import zlib
from typing import Sequence

from cdrl.data.store import DatasetError, EpisodeDataset

SHOWN = 6  # changes named one by one; the rest are counted


def _split(episodes) -> dict:
    if isinstance(episodes, EpisodeDataset):
        manifest = hashlib.sha256(json.dumps(episodes.manifest, sort_keys=True).encode()).hexdigest()
        return {"data_set": str(episodes.path), "manifest": manifest,
                "files": {name: _zip_crcs(episodes.path / name) for name in episodes.files}}
    return {"episodes": [_episode_crc(episodes[i]) for i in range(len(episodes))]}


def _zip_crcs(path) -> dict:
    try:
        with zipfile.ZipFile(path) as z:
            return {"size": path.stat().st_size, "crc32": {i.filename: i.CRC for i in z.infolist()}}
    except (OSError, zipfile.BadZipFile) as exc:
        raise DatasetError(f"episode file {path} is unreadable: {exc}") from None


def _episode_crc(episode) -> int:
    crc = 0
    for array in (episode.frames, episode.actions, episode.rewards):
        crc = zlib.crc32(array.tobytes(), crc)
    return crc


def fingerprint(train: Sequence, test: Sequence) -> dict:
    """The fingerprint of a run's training and held-out episodes (data sets or in-memory lists)."""
    return {"train": _split(train), "test": _split(test)}


def changes(old: dict, new: dict) -> list[str]:
    """What differs between fingerprints `old` and `new`, one phrase per change (the first
    `SHOWN`, then a count); empty when they are equal."""
    found: list[str] = []
    for split in ("train", "test"):
        a, b = old.get(split, {}), new.get(split, {})
        if ("files" in a) != ("files" in b):
            kind = {True: "a data set", False: "episodes made in memory"}
            found.append(f"the {split} episodes were {kind['files' in a]}, now {kind['files' in b]}")
            continue
        if "files" not in a:
            x, y = a.get("episodes", []), b.get("episodes", [])
            if len(x) != len(y):
                found.append(f"the {split} split had {len(x)} episodes, now {len(y)}")
            found += [f"{split} episode {i} differs" for i, (p, q) in enumerate(zip(x, y)) if p != q]
            continue
        if a["manifest"] != b["manifest"]:
            found.append(f"{b['data_set']}/manifest.json changed")
        for name in sorted(set(a["files"]) | set(b["files"])):
            if name not in b["files"]:
                found.append(f"{name} left the {split} split")
            elif name not in a["files"]:
                found.append(f"{name} joined the {split} split")
            elif a["files"][name] != b["files"][name]:
                found.append(f"{name} changed")
    unique = list(dict.fromkeys(found))
    if len(unique) > SHOWN:
        unique = unique[:SHOWN] + [f"and {len(unique) - SHOWN} more"]
    return unique
