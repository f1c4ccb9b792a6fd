"""The `cdrl` command's malloc (tcmalloc, `cdrl.runs.allocator`) against the system's (glibc),
on the programs that `cdrl train` runs.

Each configuration (`--configs`) runs in two worker processes, one with the library preloaded
(`LD_PRELOAD`, as the `cdrl` command re-executes itself), one on glibc's malloc, timed in
alternating windows of whole steps (which goes first alternates too):

  train:PRESET:B     the offline train step of `main` (T 32, SGD with momentum and the
                     divergence guard, the state donated: `cdrl train`'s step), from the same
                     weights on the same random chunk; frames are T x B
  online:LEARNER:PRESET
                     an online learner as `benchmarks/online_throughput.py` builds it (8 games);
                     frames are game frames

Reported per configuration: frames/s of each side (median [min, max] over `--repeats`), the
speed-up as the median [min, max] of the per-window ratios (preloaded / system), and per step
the minor page faults and the share of the process's CPU time spent in the kernel (`getrusage`).

    .venv/bin/python benchmarks/malloc_throughput.py --out benchmarks/results/allocator.json

One JSON line at the end (`--out FILE` also writes it there).
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import resource
import sys
import time

UNROLL = 32
DEFAULT_CONFIGS = ["train:thesis:1", "train:thesis:8", "online:rollout:small", "online:real:small",
                   "online:rollout:thesis"]


def _parse(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", nargs="+", default=DEFAULT_CONFIGS, metavar="KIND:...")
    ap.add_argument("--library", default=None,
                    help="the malloc library to preload (default: what CDRL_MALLOC=auto finds)")
    ap.add_argument("--seconds", type=float, default=4.0, help="timing window (default 4)")
    ap.add_argument("--repeats", type=int, default=5, help="windows per configuration and side (default 5)")
    ap.add_argument("--out", default=None, help="also write the JSON line to this file")
    return ap.parse_args(argv)


class _TrainStep:
    """`cdrl train`'s offline step of `main` at one preset and batch, its state carried on."""

    def __init__(self, preset: str, batch: int):
        import jax
        import jax.numpy as jnp
        import numpy as np

        from cdrl.data.stream import Chunk
        from cdrl.models import make_variant
        from cdrl.models.arch import preset as arch_preset
        from cdrl.training.optim import HParams
        from cdrl.training.step import init_state

        arch = arch_preset(preset)
        self.variant = make_variant("main", arch)
        self.hp = HParams.create(self.variant, lr=0.1, momentum=0.9)
        self.state = init_state(self.variant, jax.random.PRNGKey(0), batch, self.hp)
        frames = np.random.default_rng(0).integers(0, 256, (UNROLL + 1, batch, arch.image_size, arch.image_size),
                                                   dtype=np.uint8)
        is_first = np.zeros((UNROLL, batch), bool)
        is_first[0] = True
        self.chunk = Chunk(obs=jnp.asarray(frames[:-1]), next_obs=jnp.asarray(frames[1:]),
                           action=jnp.zeros((UNROLL, batch, arch.action_dim)), reward=jnp.zeros((UNROLL, batch)),
                           is_first=jnp.asarray(is_first))
        self.frames_per_step = UNROLL * batch

    def _step(self):
        from cdrl.training.step import train_step

        self.state, metrics = train_step(self.variant, self.state, self.hp, self.chunk)
        float(metrics["loss"])  # read back, as a logging loop does


def _worker(config: str, library: str | None, conn) -> None:
    """Serves timing windows of one configuration: answers each `seconds` received on `conn` with
    (frames/s, page faults per step, kernel share of CPU time), until it receives None."""
    with open("/proc/self/maps") as maps:
        loaded = library is not None and os.path.basename(library) in maps.read()
    if library is not None and not loaded:
        raise RuntimeError(f"{library} was not preloaded")
    import jax

    jax.config.update("jax_enable_compilation_cache", False)
    kind, *spec = config.split(":")
    if kind == "train":
        program = _TrainStep(spec[0], int(spec[1]))
    else:
        from online_throughput import _Program

        program = _Program(spec[0], spec[1], 8)
    for _ in range(3):  # compile, then let the heap grow to what a step holds
        program._step()
    conn.send(loaded)
    while (seconds := conn.recv()) is not None:
        n, r0, t0 = 0, resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            program._step()
            n += 1
        wall, r1 = time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_SELF)
        user, system = r1.ru_utime - r0.ru_utime, r1.ru_stime - r0.ru_stime
        conn.send((n * program.frames_per_step / wall, (r1.ru_minflt - r0.ru_minflt) / n,
                   system / max(user + system, 1e-9)))


def measure(config: str, library: str, seconds: float, repeats: int) -> dict:
    from common import alternate_windows, recv_or_fail, spread

    ctx = mp.get_context("spawn")
    pipes, workers = [], []
    saved = os.environ.pop("LD_PRELOAD", None)
    for preload in (library, None):  # one after the other: each compiles on an otherwise idle machine
        mine, theirs = ctx.Pipe()
        if preload:  # the spawned interpreter starts with it
            os.environ["LD_PRELOAD"] = preload
        w = ctx.Process(target=_worker, args=(config, preload, theirs))
        w.start()
        os.environ.pop("LD_PRELOAD", None)
        pipes.append(mine)
        workers.append(w)
        recv_or_fail(mine, w)
    if saved is not None:
        os.environ["LD_PRELOAD"] = saved
    windows = alternate_windows(pipes, workers, seconds, repeats)
    side = lambda ws: {"frames_per_s": spread([w[0] for w in ws]), "page_faults_per_step": spread([w[1] for w in ws]),  # noqa: E731
                       "kernel_share_of_cpu": spread([w[2] for w in ws])}
    return {"config": config, "preloaded": side(windows[0]), "system": side(windows[1]),
            "speedup": spread([a[0] / b[0] for a, b in zip(*windows)])}


def main(argv=None) -> int:
    from common import finish

    from cdrl.runs.allocator import allocator_library

    args = _parse(argv)
    library = args.library or allocator_library("auto")
    if library is None:
        raise SystemExit("no tcmalloc found (e.g. apt install libtcmalloc-minimal4); name one with --library")
    for config in args.configs:
        kind, *spec = config.split(":")
        if not ((kind == "train" and len(spec) == 2 and spec[1].isdigit()) or (kind == "online" and len(spec) == 2)):
            raise SystemExit(f"--configs {config!r}: expected train:PRESET:B or online:LEARNER:PRESET")
    result = {"benchmark": "allocator", "library": library, "cpu_count": os.cpu_count(),
              "seconds_per_repeat": args.seconds, "repeats": args.repeats,
              "load_avg_start": round(os.getloadavg()[0], 2), "rows": []}
    for config in args.configs:
        row = measure(config, library, args.seconds, args.repeats)
        result["rows"].append(row)
        pre, sys_, sp = row["preloaded"], row["system"], row["speedup"]
        print(f"{config:22s} preloaded {pre['frames_per_s']['median']:8.1f} frames/s, "
              f"{pre['page_faults_per_step']['median']:6.0f} faults/step, "
              f"{100 * pre['kernel_share_of_cpu']['median']:3.0f} % kernel; system "
              f"{sys_['frames_per_s']['median']:8.1f}, {sys_['page_faults_per_step']['median']:6.0f}, "
              f"{100 * sys_['kernel_share_of_cpu']['median']:3.0f} %; {sp['median']:.2f}x "
              f"[{sp['min']:.2f}, {sp['max']:.2f}]", flush=True)
    return finish(result, args.out)


if __name__ == "__main__":
    sys.exit(main())
