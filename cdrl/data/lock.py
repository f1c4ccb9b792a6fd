"""One writer per directory: an OS-level lock on a file inside it.

`DirLock(directory)` takes an exclusive `fcntl.flock` on `directory/.lock` without waiting;
if another process holds it, `LockedError` names that process's pid, which the holder
wrote into the lock file. The OS drops a flock lock when its holder exits, however it
exits, so a lock left by a killed process never blocks: the file stays, the lock does not.
Locks belong to an open file, not to a process, so a second `DirLock` on the same directory
in the same process is refused too.

A writer that fails before it writes anything leaves nothing behind: on release, a lock file
this lock created in a directory that holds nothing else is removed, and so is the directory
when this lock created it. (A writer that then takes the lock of the removed file would
lock a file no longer in the directory, so `acquire` checks that the file it locked is still
the directory's lock file, and tries again if not.)

Run directories (`cdrl.runs.rundir.RunDir.lock`) and data set directories
(`cdrl.data.writer`) use it; readers never take it.
"""
from __future__ import annotations

import errno
import fcntl
import os
from pathlib import Path

LOCK_NAME = ".lock"


class LockedError(RuntimeError):
    """Another process (named by its pid) is writing to the directory."""

    def __init__(self, message: str, pid: int | None):
        super().__init__(message)
        self.pid = pid


_ATTEMPTS = 10


def _same_file(fd: int, path: Path) -> bool:
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return False
    own = os.fstat(fd)
    return (st.st_dev, st.st_ino) == (own.st_dev, own.st_ino)


def _missing_dirs(directory: Path) -> list[Path]:
    """`directory` and those of its parents that do not exist, innermost first."""
    missing = []
    for path in (directory, *directory.parents):
        if path.exists():
            break
        missing.append(path)
    return missing


def _only_entry(directory: Path, name: str) -> bool:
    try:
        return [p.name for p in directory.iterdir()] == [name]
    except OSError:
        return False


def _holder(fd: int) -> int | None:
    os.lseek(fd, 0, os.SEEK_SET)
    text = os.read(fd, 64).decode(errors="replace").strip()
    return int(text) if text.isdigit() else None


class DirLock:
    """An exclusive, non-blocking lock on `directory` (created if needed) for one writer.

    Use as a context manager, or `acquire()` / `release()`. `what` names the directory's
    kind in the error ("run directory", "data set").
    """

    def __init__(self, directory: str | os.PathLike, what: str = "directory"):
        self.directory = Path(directory)
        self.path = self.directory / LOCK_NAME
        self.what = what
        self._fd: int | None = None
        self._made_dirs: list[Path] = []
        self._made_file = False

    def acquire(self) -> "DirLock":
        if self._fd is not None:
            raise RuntimeError(f"{self.path} is already locked by this DirLock")
        for _ in range(_ATTEMPTS):
            self._made_dirs = _missing_dirs(self.directory)
            self.directory.mkdir(parents=True, exist_ok=True)
            self._made_file = not self.path.exists()
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            except FileNotFoundError:  # the directory was tidied away meanwhile
                continue
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    os.close(fd)
                    raise
                pid = _holder(fd)
                os.close(fd)
                who = f"pid {pid}" if pid is not None else "another process"
                raise LockedError(
                    f"{self.what} {self.directory} is in use by {who} (lock file {self.path}); one writer at "
                    "a time: wait for it to finish or stop it", pid) from None
            if _same_file(fd, self.path):
                break
            os.close(fd)  # a releasing writer removed the file we locked: lock the directory's new one
        else:
            raise RuntimeError(f"could not lock {self.path}: it kept being removed")
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        os.fsync(fd)
        self._fd = fd
        return self

    def release(self) -> None:
        """Release the lock; remove the lock file (and the directories) if this lock created them
        and nothing else was written there (see the module docstring)."""
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        try:
            if self._made_file and _only_entry(self.directory, LOCK_NAME):
                self.path.unlink(missing_ok=True)
                for made in self._made_dirs:  # the directory first, then the parents this lock made
                    try:
                        made.rmdir()
                    except OSError:  # something else is in it now: keep it
                        break
            fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)

    @property
    def held(self) -> bool:
        return self._fd is not None

    def __enter__(self) -> "DirLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
