"""What every benchmark script shares: the spread of per-repeat figures and the one JSON line
at the end (printed, and written atomically to `--out FILE` when given).

The scripts run as `python benchmarks/NAME.py`, so this folder is on `sys.path` and they
import it as `common`. The studies of experiments/ put the repository root on `sys.path` and
import it as `benchmarks.common`.
"""
from __future__ import annotations

import json
import os
import statistics
import sys
from pathlib import Path

from cdrl.data.atomic import atomic_write_text


def spread(values) -> dict:
    """min / median / max of per-repeat figures, as floats."""
    values = [float(v) for v in values]
    return {"min": min(values), "median": statistics.median(values), "max": max(values)}


def emit(result: dict, out: str | Path | None) -> str:
    """Print `result` as one JSON line; with `out`, also write it there (atomically,
    `cdrl.data.atomic`: an interrupted write leaves the previous result whole)."""
    line = json.dumps(result)
    if out:
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out, line + "\n")
    print(line)
    return line


def warn_if_busy(result: dict, load_avg_start: float, load_avg_end: float) -> None:
    """Add a `warning` to `result` (and print it) when the load average at the start or the
    end of the run exceeded half the CPUs: wall-clock figures taken then are unreliable."""
    busy = max(load_avg_start, load_avg_end)
    cpus = os.cpu_count() or 1
    if busy > 0.5 * cpus:
        result["warning"] = f"machine busy (load average up to {busy:.1f} on {cpus} CPUs): wall-clock figures are unreliable"
        print("warning: " + result["warning"], file=sys.stderr, flush=True)


def recv_or_fail(pipe, proc):
    """The next message from a worker process on `pipe`; a `RuntimeError` naming its exit code
    if the worker ends first (a benchmark would otherwise wait for it forever)."""
    while not pipe.poll(1.0):
        if not proc.is_alive():
            raise RuntimeError(f"a benchmark worker ended with exit code {proc.exitcode} (its traceback is above)")
    return pipe.recv()


def checkout_commit(directory) -> str | None:
    """The commit checked out in `directory` (a git worktree), or None where git cannot say."""
    import subprocess

    try:
        return subprocess.run(["git", "-C", str(directory), "rev-parse", "HEAD"], capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def alternate_windows(pipes, workers, seconds: float, repeats: int) -> list[list]:
    """Time two (or more) worker processes in alternating windows: `repeats` rounds, each sending
    `seconds` to every worker in turn (the order reversed every other round, so that neither
    always goes first) and collecting its answer; then tells each to stop (None) and joins it.
    Returns each worker's answers, in round order."""
    answers: list[list] = [[] for _ in pipes]
    for i in range(repeats):
        for j in (range(len(pipes)) if i % 2 == 0 else reversed(range(len(pipes)))):
            pipes[j].send(seconds)
            answers[j].append(recv_or_fail(pipes[j], workers[j]))
    for p, w in zip(pipes, workers):
        p.send(None)
        w.join()
    return answers


def finish(result: dict, out: str | Path | None) -> int:
    """The end of a benchmark whose `result` holds `load_avg_start`: the load average now, the
    busy-machine warning where due (`warn_if_busy`), the JSON line (`emit`); returns 0."""
    result["load_avg_end"] = round(os.getloadavg()[0], 2)
    warn_if_busy(result, result["load_avg_start"], result["load_avg_end"])
    emit(result, out)
    return 0
