"""Checksums of a checkpoint's files, written with the checkpoint and checked before it is read.

Orbax stores no checksum of the arrays it writes: a flipped bit in a checkpoint restores as a
slightly different state and the run goes on from it. So once orbax has committed checkpoint
`<step>/`, its writer records the SHA-256 and size of every file in it, in
`<step>/checksums.json` (written atomically: `cdrl.data.atomic`), and a restore first checks
every listed file against it (`verify`). A checkpoint whose save finished but whose checksums
are missing (a kill between the two writes) is unfinished, like one orbax never committed.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

from cdrl.data.atomic import atomic_write_text

CHECKSUM_FILE = "checksums.json"
ALGORITHM = "sha256"
_BLOCK = 1 << 20


class ChecksumError(ValueError):
    """A checkpoint's files do not match the checksums saved with it (the message names the file)."""


def file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(_BLOCK):
            h.update(block)
    return h.hexdigest()


def digests(directory: Path) -> dict[str, dict]:
    """Relative path -> {"size", "sha256"} of every file under `directory` but the checksum file."""
    return {p.relative_to(directory).as_posix(): {"size": p.stat().st_size, ALGORITHM: file_digest(p)}
            for p in sorted(directory.rglob("*")) if p.is_file() and p.name != CHECKSUM_FILE}


def write_checksums(directory: Path) -> None:
    """Record the checksums of every file of the finished checkpoint `directory` in it."""
    text = json.dumps({"algorithm": ALGORITHM, "files": digests(directory)}, indent=1, sort_keys=True)
    atomic_write_text(directory / CHECKSUM_FILE, text + "\n")


def has_checksums(directory: Path) -> bool:
    return (directory / CHECKSUM_FILE).is_file()


def verify(directory: Path) -> None:
    """Check every file listed in `directory`'s checksum file: present, of its size and digest.
    Raises `ChecksumError` naming the first that is not (or an unreadable checksum file)."""
    path = directory / CHECKSUM_FILE
    try:
        listed = json.loads(path.read_text())["files"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ChecksumError(f"its checksum file {path} is unreadable ({type(exc).__name__}: {exc})") from None
    for name, want in sorted(listed.items()):
        file = directory / name
        if not file.is_file():
            raise ChecksumError(f"its file {name} is missing")
        if file.stat().st_size != want["size"] or file_digest(file) != want[ALGORITHM]:
            raise ChecksumError(f"its file {name} does not match the checksum saved with it")
