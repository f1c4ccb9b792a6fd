"""Where a compiled program's time goes: XLA's operations timed by JAX's profiler, summed by kind.

One of three programs, compiled and warmed up, then run `--calls` times under
`jax.profiler.trace` (its Perfetto trace, read back here):

  train    the jitted train step `cdrl train` runs (`cdrl.training.step.train_step`; `--variant`,
           `--preset`, B `--batch` streams x T `--unroll` frames, SGD with momentum)
  online   an online learner's program as `cdrl train` builds it (`--learner rollout|real|ppo`,
           `--preset`, `--batch` games; benchmarks/online_throughput.py's programs)
  game     the vmapped game, policy + step + drawing, `--batch` games x 64 steps a call
           (benchmarks/env_throughput.py's rollout)
  sweep    the vmapped sweep step of `--configs` configurations (`cdrl.runs.sweep.sweep_step`,
           an lr x momentum grid; benchmarks/sweep_throughput.py's program)

`--conv` picks how the train and sweep programs compute their convolutions (`ArchConfig.conv`).

Every operation event of the trace (an XLA fusion, convolution, matrix product, copy, ...;
the runtime's own events, Python's and control flow's, which contain the others, left out) is
summed by name, per call, and by kind: the name without its number, `select_add_fusion.21`
-> `select_add_fusion` (XLA names a fusion by its main operations). The sums are over both
threads of XLA's CPU runtime, so they can exceed the wall time of a call, which is timed apart
(`--calls` calls outside the profiler; the median). The slowest operations are listed with
their output shape and the JAX operation they came from (the compiled program's metadata),
e.g. `transpose(jvp())/while/body/checkpoint/jit(selu)`: the gradient of a SELU inside a scan
whose layer is recomputed.

    .venv/bin/python benchmarks/op_profile.py --program online --learner rollout --preset thesis --batch 8
    .venv/bin/python benchmarks/op_profile.py --program train --preset thesis --batch 1 --out FILE

Prints the tables, then one JSON line (`--out FILE` also writes it there).
"""
from __future__ import annotations

import argparse
import collections
import dataclasses
import gzip
import json
import os
import re
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# Trace events that are not one XLA operation: Python's frames ("$file:line name"), the jitted
# call and its transfer, and control flow (a while loop's or a call's event spans the operations
# inside it); and the runtime's own (C++ names, `ThunkExecutor::Execute`: they contain "::").
NOT_OPERATIONS = ("$", "np.asarray", "PjitFunction", "while", "conditional", "call")


def _parse(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--program", choices=["train", "online", "game", "sweep"], default="train")
    ap.add_argument("--conv", default="auto", help="convolution backend of train and sweep (default: auto)")
    ap.add_argument("--configs", type=int, default=8, help="configurations of the sweep (default: 8)")
    ap.add_argument("--preset", default="thesis", help="model preset (train, online)")
    ap.add_argument("--variant", default="main", help="model variant (train)")
    ap.add_argument("--learner", choices=["rollout", "real", "ppo"], default="rollout", help="online learner")
    ap.add_argument("--batch", type=int, default=None,
                    help="streams (train, default 1), games (online, default 8; ppo plays its own 16), "
                         "games (game, default 64)")
    ap.add_argument("--unroll", type=int, default=32, help="T of a train chunk")
    ap.add_argument("--calls", type=int, default=5, help="calls profiled (and calls timed apart)")
    ap.add_argument("--top", type=int, default=15, help="operations listed")
    ap.add_argument("--out", default=None, help="also write the final JSON line to this file")
    args = ap.parse_args(argv)
    if args.calls < 1:
        ap.error(f"--calls must be at least 1, got {args.calls}")
    return args


def operation_times(events, calls: int) -> dict[str, float]:
    """Milliseconds per call of each operation name, from Chrome-trace events (`ph` "X" with
    a `dur` in microseconds), summed over threads; the runtime's events (`NOT_OPERATIONS`, and
    names with "::") left out."""
    total = collections.Counter()
    for e in events:
        name = e.get("name", "")
        if e.get("ph") == "X" and "dur" in e and not name.startswith(NOT_OPERATIONS) and "::" not in name:
            total[name] += e["dur"]
    return {name: us / 1000.0 / calls for name, us in total.items()}


def kind(name: str) -> str:
    """An operation's kind: its name without XLA's instance number (`ynn_fusion.72` -> `ynn_fusion`)."""
    return re.sub(r"\.\d+$", "", name)


def by_kind(times: dict[str, float]) -> dict[str, float]:
    """The operations' milliseconds summed by kind, largest first."""
    kinds = collections.Counter()
    for name, ms in times.items():
        kinds[kind(name)] += ms
    return dict(kinds.most_common())


def operation_sources(hlo_text: str) -> dict[str, dict]:
    """Each instruction of a compiled program's text: its output shape and the JAX operation it
    came from (the `op_name` of its metadata; for a fusion, that of its fused computation's root)."""
    roots = {}
    for comp in re.finditer(r"^(%[\w.\-]+) [^\n]*\{\n(.*?)\n\}", hlo_text, re.M | re.S):
        root = re.search(r"ROOT [^\n]*?op_name=\"([^\"]*)\"", comp.group(2))
        if root:
            roots[comp.group(1)] = root.group(1)
    sources = {}
    for m in re.finditer(r"^\s*(?:ROOT )?%([\w.\-]+) = (\S+) [^\n]*", hlo_text, re.M):
        line = m.group(0)
        op = re.search(r"op_name=\"([^\"]*)\"", line)
        called = re.search(r"calls=(%[\w.\-]+)", line)
        source = roots.get(called.group(1)) if called else None
        sources[m.group(1)] = {"shape": m.group(2), "source": source or (op.group(1) if op else "")}
    return sources


def _profile(fn, calls: int) -> list:
    """The Chrome-trace events of `calls` calls of `fn` (each ending in a blocking read)."""
    import jax

    with tempfile.TemporaryDirectory() as d:
        with jax.profiler.trace(d, create_perfetto_trace=True):
            for _ in range(calls):
                fn()
        (trace,) = Path(d).rglob("*perfetto_trace.json.gz")
        with gzip.open(trace) as f:
            data = json.load(f)
    return data["traceEvents"] if isinstance(data, dict) else data


def _train_program(args):
    """(call, compiled text, description) of the train step on random uint8 frames."""
    import jax
    import jax.numpy as jnp

    from cdrl.data.stream import Chunk
    from cdrl.models import make_variant
    from cdrl.models.arch import PRESETS
    from cdrl.training.optim import HParams
    from cdrl.training.step import init_state, train_step
    from train_throughput import _chunk_arrays

    batch, unroll = args.batch or 1, args.unroll
    arch = dataclasses.replace(PRESETS[args.preset], conv=args.conv)
    variant = make_variant(args.variant, arch)
    hp = HParams.create(variant, lr=0.1, momentum=0.9)
    obs, next_obs, is_first = _chunk_arrays(arch, unroll, batch, 0)
    chunk = Chunk(obs=jnp.asarray(obs), next_obs=jnp.asarray(next_obs),
                  action=jnp.zeros((unroll, batch, arch.action_dim), jnp.float32),
                  reward=jnp.zeros((unroll, batch), jnp.float32), is_first=jnp.asarray(is_first))
    box = [init_state(variant, jax.random.PRNGKey(0), batch, hp)]
    text = train_step.lower(variant, box[0], hp, chunk).compile().as_text()

    def call():
        box[0], metrics = train_step(variant, box[0], hp, chunk)
        float(metrics["loss"])

    return call, text, {"variant": args.variant, "preset": args.preset, "conv": args.conv, "batch": batch,
                        "unroll": unroll, "frames_per_call": batch * unroll}


def _sweep_program(args):
    """(call, compiled text, description) of `--configs` configurations' vmapped train step."""
    import jax
    import numpy as np

    from cdrl.models import make_variant
    from cdrl.models.arch import PRESETS
    from cdrl.runs.config import RunConfig
    from cdrl.runs.sweep import Grid, init_sweep, sweep_step
    from sweep_throughput import chunk

    batch, unroll, n = args.batch or 1, args.unroll, args.configs
    arch = dataclasses.replace(PRESETS[args.preset], conv=args.conv)
    variant = make_variant(args.variant, arch)
    base = RunConfig(variant=args.variant, preset=args.preset, batch=batch, unroll=unroll, conv=args.conv)
    cfgs = Grid(lr=tuple(0.1 / 2 ** i for i in range(n))).configs(base)
    chunks = chunk(np.random.default_rng(0), arch, unroll, batch, lead=(n,))
    states, hps = init_sweep(variant, cfgs)
    box = [states, np.ones((n,), bool)]
    text = sweep_step.lower(variant, states, hps, box[1], chunks).compile().as_text()

    def call():
        box[0], box[1], metrics = sweep_step(variant, box[0], hps, box[1], chunks)
        jax.block_until_ready(metrics["loss"])

    return call, text, {"variant": args.variant, "preset": args.preset, "conv": args.conv, "configs": n,
                        "batch": batch, "unroll": unroll, "frames_per_call": n * batch * unroll}


def _online_program(args):
    import jax

    from online_throughput import _Program

    program = _Program(args.learner, args.preset, args.batch or 8)
    learner = program.program
    text = learner.step.lower(learner.model, learner.game, learner.config, program.state, learner.hp,
                              learner.env_params).compile().as_text()
    jax.block_until_ready(program.state)
    return program._step, text, {**program.describe, "frames_per_call": program.frames_per_step}


def _game_program(args):
    import jax

    from env_throughput import _Rollout

    batch = args.batch or 64
    rollout = _Rollout("uniform", 64, batch)
    text = rollout.rollout.lower(rollout.carry).compile().as_text()
    jax.block_until_ready(rollout.carry)
    return rollout._call, text, {"policy": "uniform", "batch": batch, "steps": 64, "frames_per_call": batch * 64}


PROGRAMS = {"train": _train_program, "online": _online_program, "game": _game_program, "sweep": _sweep_program}


def main(argv=None) -> int:
    from common import finish

    args = _parse(argv)
    load_avg_start = os.getloadavg()[0]
    call, text, described = PROGRAMS[args.program](args)
    for _ in range(2):  # compiled by the builder or the first call; warm
        call()
    walls = []
    for _ in range(args.calls):
        t0 = time.perf_counter()
        call()
        walls.append(1000.0 * (time.perf_counter() - t0))
    times = operation_times(_profile(call, args.calls), args.calls)
    kinds = by_kind(times)
    sources = operation_sources(text)
    wall = statistics.median(walls)
    summed = sum(times.values())
    print(f"{args.program}: {described}")
    print(f"wall {wall:.1f} ms a call (median of {args.calls}); operations {summed:.1f} ms a call summed over threads")
    print(f"{'ms/call':>9} {'share':>6}  kind")
    for k, ms in list(kinds.items())[:args.top]:
        print(f"{ms:9.2f} {ms / summed:6.1%}  {k}")
    top = sorted(times.items(), key=lambda kv: -kv[1])[:args.top]
    print(f"{'ms/call':>9}  operation, output, from")
    rows = []
    for name, ms in top:
        src = sources.get(name, {})
        rows.append({"name": name, "ms_per_call": round(ms, 3), "shape": src.get("shape"),
                     "source": src.get("source")})
        print(f"{ms:9.2f}  {name} {src.get('shape', '?')} {src.get('source', '')[-100:]}")
    result = {"program": args.program, **described, "calls": args.calls,
              "wall_ms_per_call": round(wall, 2), "wall_ms_repeats": [round(w, 2) for w in walls],
              "frames_per_s": round(described["frames_per_call"] / wall * 1000.0, 1),
              "operations_ms_per_call": round(summed, 2),
              "by_kind_ms_per_call": {k: round(ms, 3) for k, ms in kinds.items()},
              "top_operations": rows, "load_avg_start": round(load_avg_start, 2)}
    return finish(result, args.out)


if __name__ == "__main__":
    sys.path.insert(0, ROOT)
    sys.exit(main())
