"""JAX's persistent compilation cache for every `cdrl` command: a second run of the same
configuration loads every program it compiled the first time instead of compiling it again."""
from __future__ import annotations

import os
from pathlib import Path


def cache_dir() -> Path:
    """Where compiled programs are kept: $CDRL_COMPILE_CACHE, else JAX's own
    $JAX_COMPILATION_CACHE_DIR, else $XDG_CACHE_HOME/cdrl/xla (~/.cache/cdrl/xla)."""
    for name in ("CDRL_COMPILE_CACHE", "JAX_COMPILATION_CACHE_DIR"):
        if os.environ.get(name):
            return Path(os.environ[name])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "cdrl" / "xla"


def use(directory: Path) -> None:
    """Keep every compiled program in `directory`, however quick to compile (JAX's defaults
    skip those under a second). Setting it touches no backend, so `--distributed` can still
    join its processes afterwards."""
    import jax

    jax.config.update("jax_compilation_cache_dir", str(directory))
    jax.config.update("jax_persistent_cache_min_compile_time_secs",
                      float(os.environ.get("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", 0.0)))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
