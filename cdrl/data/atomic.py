"""Atomic file writes: readers see a file's old content or its complete new content, never a
part, and a crash leaves at most a temporary file beside it.

A write fills a temporary file in the same directory (its name starts with ``.tmp-``), which is
flushed, fsync-ed and renamed over the final name; the directory is then fsync-ed so that the
rename itself survives a power cut.  Episode files and manifests (:mod:`cdrl.data.store`), run
directories' files (``cdrl.runs``), figures and benchmark results are all written this way.
"""
from __future__ import annotations

import os
import secrets
from pathlib import Path
from typing import Any, Callable

TEMP_PREFIX = ".tmp-"


def fsync_dir(path: str | os.PathLike) -> None:
    """fsync the directory ``path`` (where the platform allows it), making renames in it durable."""
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


def _open_temp(path: Path, mode: int | None) -> tuple[int, Path]:
    """A new temporary file beside ``path``, open for writing: its descriptor and path."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0) | getattr(os, "O_CLOEXEC", 0)
    while True:
        tmp = path.parent / f"{TEMP_PREFIX}{path.name}.{secrets.token_hex(4)}"
        try:
            fd = os.open(tmp, flags, 0o666 if mode is None else mode)
        except FileExistsError:
            continue
        if mode is not None:
            os.chmod(tmp, mode)  # exactly `mode`, whatever the umask
        return fd, tmp


def atomic_write(path: str | os.PathLike, write: Callable[[Any], None], mode: int | None = None) -> None:
    """Writes ``path`` atomically: ``write(file)`` fills a temporary binary file in the same
    directory, which is flushed, fsync-ed and renamed over ``path``.  On any error the
    temporary file is removed and ``path`` is left as it was.

    ``mode``: the new file's permission bits (None: those ``open()`` gives, 0o666 less the
    umask)."""
    path = Path(path)
    fd, tmp = _open_temp(path, mode)
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
    fsync_dir(path.parent)


def atomic_write_text(path: str | os.PathLike, text: str, mode: int | None = None) -> None:
    """Writes the string ``text`` (UTF-8) to ``path`` atomically, as :func:`atomic_write`."""
    data = text.encode("utf-8")
    atomic_write(path, lambda f: f.write(data), mode)
