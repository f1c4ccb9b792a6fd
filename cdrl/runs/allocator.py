"""Run the `cdrl` command under tcmalloc where it is installed.

XLA's CPU runtime allocates a compiled program's scratch buffer (107 MB for the thesis-sized
train step at one stream) with `malloc` at every call and frees it after. glibc's allocator
maps a block that large afresh each time and unmaps it when it is freed, so every call faults
each page of it in again: some 37 000 page faults a thesis-sized step at one stream, a quarter
of the step's CPU time spent in the kernel. gperftools' tcmalloc keeps freed memory for reuse,
and the same step runs 1.38x faster under it at one stream, 1.45x at eight
(`benchmarks/malloc_throughput.py`, docs/performance.md). glibc's own settings do not do it: the
arenas of XLA's worker threads map every block over 64 MB whatever they are told, and a single
shared arena (`MALLOC_ARENA_MAX=1`) removes the faults but makes the online programs' threads
queue for it (half their speed).

The `cdrl` command re-executes itself once with the library in `LD_PRELOAD`
(`reexec_with_allocator`), as Intel's PyTorch launcher does. `CDRL_MALLOC` chooses: `auto`
(the default: tcmalloc where the dynamic linker finds it, e.g. Debian's and Ubuntu's
`libtcmalloc-minimal4`, else the system's malloc), `system` (never), or the path of a malloc
library to preload. From Python (a notebook, a script), start the interpreter with
`LD_PRELOAD=libtcmalloc_minimal.so.4` for the same effect.
"""
from __future__ import annotations

import ctypes.util
import os
import sys

ENV = "CDRL_MALLOC"
# Set in the re-executed process: the library it was given (so it never re-executes twice).
PRELOADED_ENV = "CDRL_MALLOC_PRELOADED"
CANDIDATES = ("tcmalloc_minimal", "tcmalloc")


def allocator_library(choice: str | None = None) -> str | None:
    """The malloc library `CDRL_MALLOC` (or `choice`) asks for: a name the dynamic linker finds
    or a path; None for the system's malloc. Raises `ValueError` naming a path that is not a file."""
    choice = os.environ.get(ENV, "auto") if choice is None else choice
    if choice == "system":
        return None
    if choice == "auto":
        if not sys.platform.startswith("linux"):
            return None
        return next((found for name in CANDIDATES if (found := ctypes.util.find_library(name))), None)
    if not os.path.isfile(choice):
        raise ValueError(f"{ENV}={choice!r}: expected auto, system or the path of a malloc library to preload "
                         "(no such file)")
    return choice


def preload_environment(environ: dict[str, str], library: str | None) -> dict[str, str] | None:
    """The environment to re-execute with, `library` first in `LD_PRELOAD`; None where there is
    nothing to do: no library, this process already re-executed, or the library preloaded already."""
    if library is None or environ.get(PRELOADED_ENV):
        return None
    preloads = [p for p in environ.get("LD_PRELOAD", "").replace(" ", ":").split(":") if p]
    if any(os.path.basename(p) == os.path.basename(library) for p in preloads):
        return None
    env = {**environ, "LD_PRELOAD": ":".join([library, *preloads]), PRELOADED_ENV: library}
    # tcmalloc reports every allocation over 1 GB on stderr, which a large batch's scratch buffer is
    env.setdefault("TCMALLOC_LARGE_ALLOC_REPORT_THRESHOLD", str(2**40))
    return env


def reexec_with_allocator() -> None:
    """Replace this process by the same command with the library of `allocator_library`
    preloaded, once; return where there is nothing to do. Call it first thing, before any
    thread starts or any file is written. A library the dynamic linker cannot load is skipped
    with its message, and the command runs on the system's malloc."""
    env = preload_environment(dict(os.environ), allocator_library())
    if env is None:
        return
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]], env)
