"""Test-session setup, inherited by the `cdrl` subprocesses and notebook kernels the tests start:

* one persistent XLA compilation cache for the session's workers and the processes they start,
  so a program compiled once is not compiled again by any of them;
* XLA's CPU backend without LLVM optimisation, except where CDRL_TEST_XLA_OPT=default. Most of
  the suite's time is XLA compiling programs that then run a few steps of the tiny preset;
  unoptimised machine code compiles about a quarter faster overall and computes the same
  numbers (the HLO passes, which decide the arithmetic, still run). The tests marked
  `default_opt` run at the default level, which is what users run and the benchmarks time.
"""
import os
import tempfile

import jax
import pytest

NO_LLVM_OPT = "--xla_backend_optimization_level=0"
# CDRL_TEST_XLA_OPT=default: compile at XLA's default level, as users' programs and the
# benchmarks do. `make test` runs the tests that pin numbers (marked `default_opt`: the PyTorch
# reference, the convolutions' values and gradients, exact resume, the learning test) in a
# second session at that level, the rest without LLVM optimisation.
DEFAULT_OPT = os.environ.get("CDRL_TEST_XLA_OPT") == "default"
if not DEFAULT_OPT and NO_LLVM_OPT not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {NO_LLVM_OPT}".strip()
# One cache for the session's workers (pytest-xdist, `make test`) and the `cdrl` processes and
# notebook kernels they start, one per optimisation level. Two processes writing and reading an
# entry at the same moment would read a truncated file: a size limit turns on JAX's file lock
# around every read and write of the cache (the limit is far above what the suite writes).
_BASE = os.environ.setdefault("CDRL_TEST_XLA_CACHE", os.environ.get("JAX_COMPILATION_CACHE_DIR")
                              or tempfile.mkdtemp(prefix="cdrl-test-xla-"))
_CACHE = os.path.join(_BASE, "default-opt" if DEFAULT_OPT else "no-llvm-opt")
CACHE_LIMIT = 8 << 30
os.environ["JAX_COMPILATION_CACHE_DIR"] = _CACHE
os.environ["JAX_COMPILATION_CACHE_MAX_SIZE"] = str(CACHE_LIMIT)
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")
jax.config.update("jax_compilation_cache_dir", _CACHE)
jax.config.update("jax_compilation_cache_max_size", CACHE_LIMIT)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop the compiled programs of a test module when it ends. Each one stays mapped in the
    worker until JAX's caches are cleared, about six memory maps a program (measured), and the
    kernel allows 65 530: a worker that kept the whole suite's programs segfaulted in XLA while
    serialising the next one (a fresh clone's `make test`, in test_online). A later module that
    needs a program again loads it from the persistent cache."""
    yield
    jax.clear_caches()
