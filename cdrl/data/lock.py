"""One writer per directory: an OS-level lock on a file inside it.

`DirLock(directory)` takes an exclusive `fcntl.flock` on `directory/.lock` without waiting;
if another process holds it, `LockedError` names that process's pid, which the holder
wrote into the lock file. The OS drops a flock lock when its holder exits, however it
exits, so a lock left by a killed process never blocks: the file stays, the lock does not.
Locks belong to an open file, not to a process, so a second `DirLock` on the same directory
in the same process is refused too.

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

    def acquire(self) -> "DirLock":
        if self._fd is not None:
            raise RuntimeError(f"{self.path} is already locked by this DirLock")
        self.directory.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
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
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        os.fsync(fd)
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        try:
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
