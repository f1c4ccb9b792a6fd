"""Several processes, one program: `jax.distributed` from the environment, and what the
processes of a run share.

`initialize()` (`cdrl train --distributed`, `cdrl sweep --distributed`) joins this process to
the others before JAX starts its backends: from `JAX_COORDINATOR_ADDRESS` (host:port of
process 0), `JAX_NUM_PROCESSES` and `JAX_PROCESS_ID`, or, where those are unset, from a
cluster JAX detects itself (SLURM's `SLURM_*` variables, Open MPI, Kubernetes, Cloud TPU).
CPU devices talk through gloo collectives. After it, `jax.devices()` lists every process's
devices and every process runs the same program on global arrays.

The helpers below are what the processes of one run do together: gathering small
JSON-able results to every process (`multihost_utils.process_allgather`), and running a step
on process 0 before the others (collecting a data set once). With one process they are plain
calls.
"""
from __future__ import annotations

import json
import os
from typing import Callable, TypeVar

import jax
import numpy as np
from jax.experimental import multihost_utils

ENV = ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID")
T = TypeVar("T")


class DistributedError(RuntimeError):
    """The processes could not be joined, or another process of the run failed."""


def initialize() -> dict:
    """Join the processes of a run (see the module docstring). Returns this process's index,
    the process count and the global device count. `DistributedError` names what is missing."""
    given = {name: os.environ.get(name) for name in ENV}
    if any(given.values()) and not all(given.values()):
        missing = ", ".join(name for name, value in given.items() if not value)
        raise DistributedError(f"--distributed: {missing} unset; set all of {', '.join(ENV)} (or none, "
                               "inside a cluster job JAX detects, such as SLURM's srun)")
    try:
        count = int(given["JAX_NUM_PROCESSES"]) if given["JAX_NUM_PROCESSES"] else None
        index = int(given["JAX_PROCESS_ID"]) if given["JAX_PROCESS_ID"] else None
    except ValueError:
        raise DistributedError(f"--distributed: JAX_NUM_PROCESSES and JAX_PROCESS_ID must be integers, got "
                               f"{given['JAX_NUM_PROCESSES']!r} and {given['JAX_PROCESS_ID']!r}") from None
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    try:
        jax.distributed.initialize(coordinator_address=given["JAX_COORDINATOR_ADDRESS"], num_processes=count,
                                   process_id=index)
    except ValueError as exc:
        raise DistributedError(f"--distributed: {exc} Set {', '.join(ENV)}, or run inside a cluster job that JAX "
                               "detects (SLURM's srun, Open MPI's mpirun)") from None
    return {"process": jax.process_index(), "processes": jax.process_count(), "devices": jax.device_count()}


def is_primary() -> bool:
    """Whether this is process 0, which writes the files of the run as a whole."""
    return jax.process_index() == 0


def allgather_json(value) -> list:
    """`value` (anything `json.dumps` takes) of every process, in process order."""
    if jax.process_count() == 1:
        return [value]
    data = np.frombuffer(json.dumps(value).encode(), np.uint8)
    sizes = np.asarray(multihost_utils.process_allgather(np.array([data.size], np.int32))).reshape(-1)
    padded = np.zeros(int(sizes.max()), np.uint8)
    padded[:data.size] = data
    gathered = np.asarray(multihost_utils.process_allgather(padded))
    return [json.loads(gathered[p, :sizes[p]].tobytes().decode()) for p in range(len(sizes))]


def all_or_none(fn: Callable[[], T], what: str) -> T:
    """`fn()` on every process; when it raises on any of them it raises on all (the failed
    process its own error, the others `DistributedError` with that error's message), so no
    process waits at a later collective for one that has stopped."""
    error = None
    try:
        result = fn()
    except Exception as exc:  # noqa: BLE001 - re-raised below, after the others have heard of it
        error = exc
    failed = [(p, e) for p, e in enumerate(allgather_json(None if error is None else f"{type(error).__name__}: {error}"))
              if e is not None]
    if error is not None:
        raise error
    if failed:
        p, message = failed[0]
        raise DistributedError(f"{what} failed on process {p}: {message}")
    return result


def primary_first(fn: Callable[[], T], what: str) -> T:
    """`fn()` on process 0, then on the others (a data set collected once, then read)."""
    first = all_or_none(fn if is_primary() else (lambda: None), what)
    later = all_or_none((lambda: None) if is_primary() else fn, what)
    return first if is_primary() else later
