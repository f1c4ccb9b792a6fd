"""Sweep throughput: N configurations as one vmapped program against the same N runs one
after another.

Both sides run the same train step (`cdrl.training.step.train_step_fn`: the variant, SGD with
momentum, the norm-ratio monitor, the divergence selects) on the same synthetic chunks:
  * sequential: N separate states, each advanced by the jitted single-config `train_step`
    (one compiled program shared by all N), config after config;
  * sweep: one stacked state advanced by `cdrl.runs.sweep.sweep_step` (one compiled program).
After warm-up (both compile), `--repeats` alternating repeats of `--steps` steps per config;
reported: training frames/s of each (all configs' frames; median over repeats), their ratio,
compile times. One JSON line at the end.

    .venv/bin/python benchmarks/sweep_throughput.py               # small preset, B 1, 8 configs
    .venv/bin/python benchmarks/sweep_throughput.py --preset thesis --steps 2
"""
from __future__ import annotations

import argparse
import json
import os
import time

import jax
import numpy as np

from cdrl.data.stream import Chunk
from cdrl.models import make_variant
from cdrl.models.arch import preset
from cdrl.runs.config import RunConfig
from cdrl.runs.sweep import Grid, init_sweep, sweep_step, take
from cdrl.training.step import train_step


def chunk(rng, arch, T: int, B: int, lead: tuple[int, ...] = ()) -> Chunk:
    s = arch.image_size
    frames = rng.integers(0, 256, lead + (T + 1, B, s, s), dtype=np.uint8)
    return Chunk(obs=frames[..., :-1, :, :, :], next_obs=frames[..., 1:, :, :, :],
                 action=rng.random(lead + (T, B, arch.action_dim), dtype=np.float32),
                 reward=np.zeros(lead + (T, B), np.float32), is_first=np.zeros(lead + (T, B), bool))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variant", default="main", help="model variant (default: main)")
    parser.add_argument("--preset", default="small", help="architecture preset (default: small)")
    parser.add_argument("--configs", type=int, default=8, help="configurations N (default: 8)")
    parser.add_argument("--batch", type=int, default=1, help="streams per config B (default: 1)")
    parser.add_argument("--unroll", type=int, default=32, help="T (default: 32)")
    parser.add_argument("--steps", type=int, default=5, help="steps per config per repeat (default: 5)")
    parser.add_argument("--repeats", type=int, default=3, help="alternating repeats (default: 3)")
    args = parser.parse_args(argv)

    arch = preset(args.preset)
    variant = make_variant(args.variant, arch)
    n, T, B = args.configs, args.unroll, args.batch
    # An lr x momentum grid of N points (2 momenta when N is even).
    moms = (0.9, 0.5) if n % 2 == 0 else (0.9,)
    lrs = tuple(0.1 / 2 ** i for i in range(n // len(moms)))
    base = RunConfig(variant=args.variant, preset=args.preset, batch=B, unroll=T)
    cfgs = Grid(lr=lrs, momentum=moms).configs(base)
    rng = np.random.default_rng(0)
    chunks = chunk(rng, arch, T, B, lead=(n,))
    singles = [take(chunks, i) for i in range(n)]

    states, hps = init_sweep(variant, cfgs)
    seq_states = [take(states, i) for i in range(n)]
    seq_hps = [take(hps, i) for i in range(n)]
    alive = np.ones((n,), bool)

    t0 = time.perf_counter()
    states, alive, m = sweep_step(variant, states, hps, alive, chunks)
    jax.block_until_ready(m["loss"])
    compile_sweep = time.perf_counter() - t0
    t0 = time.perf_counter()
    for i in range(n):
        seq_states[i], m = train_step(variant, seq_states[i], seq_hps[i], singles[i])
        jax.block_until_ready(m["loss"])
        if i == 0:
            compile_single = time.perf_counter() - t0

    frames = n * T * B * args.steps
    seq_fps, sweep_fps = [], []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        for i in range(n):
            for _ in range(args.steps):
                seq_states[i], m = train_step(variant, seq_states[i], seq_hps[i], singles[i])
                float(m["loss"])
        seq_fps.append(frames / (time.perf_counter() - t0))
        t0 = time.perf_counter()
        for _ in range(args.steps):
            states, alive, m = sweep_step(variant, states, hps, alive, chunks)
            np.asarray(m["loss"])
        sweep_fps.append(frames / (time.perf_counter() - t0))

    result = {
        "benchmark": "sweep_throughput", "variant": args.variant, "preset": args.preset, "configs": n,
        "batch": B, "unroll": T, "steps_per_repeat": args.steps, "repeats": args.repeats,
        "cpu_count": os.cpu_count(), "load_avg_start": os.getloadavg()[0],
        "sequential_frames_per_s": float(np.median(seq_fps)), "sweep_frames_per_s": float(np.median(sweep_fps)),
        "sequential_repeats": [round(x, 1) for x in seq_fps], "sweep_repeats": [round(x, 1) for x in sweep_fps],
        "compile_single_s": compile_single, "compile_sweep_s": compile_sweep,
    }
    result["speedup"] = result["sweep_frames_per_s"] / result["sequential_frames_per_s"]
    print(f"{args.variant} {args.preset} N={n} B={B} T={T}: {n} runs one after another "
          f"{result['sequential_frames_per_s']:.0f} frames/s, one vmapped sweep {result['sweep_frames_per_s']:.0f} "
          f"frames/s: x{result['speedup']:.2f} (compile {compile_single:.1f} s single, {compile_sweep:.1f} s sweep)")
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
