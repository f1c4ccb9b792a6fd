"""Sweep throughput: N configurations as one vmapped program against the same N runs one
after another.

Both sides run the same train step (`cdrl.training.step.train_step_fn`: the variant, SGD with
momentum, the norm-ratio monitor, the divergence selects) on the same synthetic chunks:
  * sequential: N separate states, each advanced by the jitted single-config `train_step`
    (one compiled program shared by all N), config after config;
  * sweep: one stacked state advanced by `cdrl.runs.sweep.sweep_step` (one compiled program).
After warm-up (both compile), `--repeats` alternating repeats of `--steps` steps per config
(sequential, then sweep, then sequential, ...). Reported: training frames/s of each (all configs'
frames; median over repeats, and every repeat), compile times, and the speed-up sweep /
sequential with its spread:

  * `speedup`: median sweep frames/s over median sequential frames/s (as before);
  * `ratio_repeats`: the speed-up of each repeat (its sweep frames/s over the sequential frames/s
    measured just before it, in the same repeat), and `ratio_min`, `ratio_median`, `ratio_max` of
    those per-repeat ratios;
  * `target` (for an 8-config sweep: 2x at the tiny preset, 1.3x at small, 1x at thesis; null
    otherwise) and `target_met`: true only when `ratio_median` reaches it
    (`target_met_all_repeats`: when `ratio_min` does too);
  * `load_avg_start`, `load_avg_end`: the 1-minute load average before and after (wall-clock
    figures depend on what else runs on the machine).

Prints a summary line, then one JSON line at the end (`--out FILE` also writes that line to FILE;
committed results go to benchmarks/results/sweep_throughput.json).

    .venv/bin/python benchmarks/sweep_throughput.py               # small preset, B 1, 8 configs
    .venv/bin/python benchmarks/sweep_throughput.py --preset thesis --steps 2
    .venv/bin/python benchmarks/sweep_throughput.py --quick       # tiny preset, a smoke test

With `--learner NAME` (`ppo`, `onpolicy_ac`, ...) it measures a sweep of a learner that plays the
game instead: N seeds as lanes of `cdrl.runs.learner_sweep.learner_sweep_step` against the same N
learners stepped one after another by `cdrl.learners.train_program` (B games x T steps each;
defaults B 4, T 16, 2 steps per repeat; a learner with a world model trains final_proposal unless
`--variant` names another). Frames are game frames played and learnt from; the compile times of
both sides (and the lanes' init) are reported beside them; the target is 2x for any preset.

    .venv/bin/python benchmarks/sweep_throughput.py --learner ppo --out benchmarks/results/sweep_throughput_ppo.json
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path

import jax
import numpy as np

from cdrl.data.stream import Chunk
from cdrl.models import make_variant
from cdrl.models.arch import preset
from cdrl.runs.config import RunConfig
from cdrl.runs.sweep import Grid, init_sweep, sweep_step, take
from cdrl.training.step import train_step
from common import emit, spread, warn_if_busy


def chunk(rng, arch, T: int, B: int, lead: tuple[int, ...] = ()) -> Chunk:
    s = arch.image_size
    frames = rng.integers(0, 256, lead + (T + 1, B, s, s), dtype=np.uint8)
    return Chunk(obs=frames[..., :-1, :, :, :], next_obs=frames[..., 1:, :, :, :],
                 action=rng.random(lead + (T, B, arch.action_dim), dtype=np.float32),
                 reward=np.zeros(lead + (T, B), np.float32), is_first=np.zeros(lead + (T, B), bool))


# The target speed-up of a sweep over running its configurations one after another, by preset
# and number of configurations.
TARGETS = {("tiny", 8): 2.0, ("small", 8): 1.3, ("thesis", 8): 1.0}
# The target of the sweep over PyTorch training the same configurations one after another.
TORCH_TARGETS = {("small", 8): 1.5}
# The target of an 8-seed sweep of a learner that plays the game (issue 48), at any preset.
LEARNER_TARGET = 2.0


def timed(fn, *args):
    """(fn(*args) with its metrics on the host, seconds)."""
    t0 = time.perf_counter()
    out = fn(*args)
    jax.block_until_ready(out)
    return out, time.perf_counter() - t0


def alternate(args, n: int, frames: int, one, swept, then=None) -> tuple[list[float], list[float]]:
    """Frames per second of `args.repeats` alternating repeats: the N configurations one after
    another (`one(i)`, a step of configuration i), then the sweep (`swept()`, a step of all),
    `args.steps` steps each, then `then()` where given (timed by itself). Both return a loss,
    read back to the host after every step."""
    seq_fps, sweep_fps = [], []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        for i in range(n):
            for _ in range(args.steps):
                float(one(i))
        seq_fps.append(frames / (time.perf_counter() - t0))
        t0 = time.perf_counter()
        for _ in range(args.steps):
            np.asarray(swept())
        sweep_fps.append(frames / (time.perf_counter() - t0))
        if then is not None:
            then()
    return seq_fps, sweep_fps


def learner_result(args) -> dict:
    """The `--learner` measurement: N seeds swept against N runs one after another."""
    from cdrl.learners import learner_class, train_program
    from cdrl.runs.learner_sweep import LearnerSweepJob, learner_sweep_step

    n, T, B = args.configs, args.unroll, args.batch
    variant = args.variant if args.variant != "main" or not learner_class(args.learner).has_world_model \
        else "final_proposal"
    base = RunConfig(learner=args.learner, variant=variant, preset=args.preset, batch=B, unroll=T, conv=args.conv)
    cfgs = Grid(seed=tuple(range(n))).configs(base)
    job = LearnerSweepJob(cfgs)
    (states, _), init_s = timed(job.init)
    alive = job.alive
    (states, alive, _), compile_sweep = timed(learner_sweep_step, job.learner, states, alive)
    seq = [lrn.init(jax.random.PRNGKey(c.seed)) for lrn, c in zip(job.built, cfgs)]
    (seq[0], _), compile_single = timed(train_program, job.built[0], seq[0])
    for i in range(1, n):
        seq[i], m = train_program(job.built[i], seq[i])
        float(m["loss"])

    def one(i):
        seq[i], m = train_program(job.built[i], seq[i])
        return m["loss"]

    def swept():
        nonlocal states, alive
        states, alive, m = learner_sweep_step(job.learner, states, alive)
        return m["loss"]

    seq_fps, sweep_fps = alternate(args, n, n * T * B * args.steps, one, swept)
    return {"benchmark": "sweep_throughput", "learner": args.learner, "variant": variant, "preset": args.preset,
            "conv": args.conv,
            "configs": n, "swept": "seed", "batch": B, "unroll": T, "steps_per_repeat": args.steps,
            "repeats": args.repeats, "lanes_alive": int(np.sum(np.asarray(alive))),
            "seq_fps": seq_fps, "sweep_fps": sweep_fps, "compile_single_s": compile_single,
            "compile_sweep_s": compile_sweep, "init_lanes_s": init_s, "target": LEARNER_TARGET}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variant", default="main", help="model variant (default: main)")
    parser.add_argument("--preset", default=None, help="architecture preset (default: small; --quick: tiny)")
    parser.add_argument("--configs", type=int, default=8, help="configurations N (default: 8)")
    parser.add_argument("--batch", type=int, default=1, help="streams per config B (default: 1)")
    parser.add_argument("--unroll", type=int, default=None, help="T (default: 32; --quick: 8)")
    parser.add_argument("--steps", type=int, default=None, help="steps per config per repeat (default: 5; --quick: 2)")
    parser.add_argument("--repeats", type=int, default=3, help="alternating repeats (default: 3)")
    parser.add_argument("--quick", action="store_true", help="a smoke test: tiny preset, T 8, 2 steps per repeat")
    parser.add_argument("--out", type=Path, default=None, help="also write the final JSON line to this file")
    parser.add_argument("--torch", action="store_true",
                        help="also train the configurations one after another with PyTorch's reference (its own "
                             "process, each repeat after the sweep); reports sweep / torch")
    parser.add_argument("--conv", default="auto",
                        help="how the convolutions are computed (cdrl.models.conv.FORMULATIONS; default: auto)")
    parser.add_argument("--learner", default=None,
                        help="measure a sweep of this learner that plays the game over N seeds (default: none, offline)")
    args = parser.parse_args(argv)
    defaults = {"preset": "tiny", "unroll": 8, "steps": 2} if args.quick else {"preset": "small", "unroll": 32, "steps": 5}
    if args.learner:
        defaults = {**defaults, "unroll": 8 if args.quick else 16, "steps": 2}
        if args.batch == 1:
            args.batch = 4
    for name, value in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    load_avg_start = os.getloadavg()[0]
    if args.learner:
        return report_learner(learner_result(args), load_avg_start, args.out)

    arch = dataclasses.replace(preset(args.preset), conv=args.conv)
    variant = make_variant(args.variant, arch)
    n, T, B = args.configs, args.unroll, args.batch
    # An lr x momentum grid of N points (2 momenta when N is even).
    moms = (0.9, 0.5) if n % 2 == 0 else (0.9,)
    lrs = tuple(0.1 / 2 ** i for i in range(n // len(moms)))
    base = RunConfig(variant=args.variant, preset=args.preset, batch=B, unroll=T, conv=args.conv)
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

    def one(i):
        seq_states[i], m = train_step(variant, seq_states[i], seq_hps[i], singles[i])
        return m["loss"]

    def swept():
        nonlocal states, alive
        states, alive, m = sweep_step(variant, states, hps, alive, chunks)
        return m["loss"]

    torch_fps = []
    if args.torch:
        # PyTorch's configurations differ only in their learning rate and momentum, so one model
        # trained n * steps steps is their time one after another.
        from train_throughput import TorchWorker

        c0 = take(chunks, 0)
        worker = TorchWorker(arch, args.variant, take(states.params, 0),
                             (c0.obs, c0.next_obs, c0.is_first), os.cpu_count())
        worker.run(2)  # warm

        def torch_one_after_another():
            step_s, _ = worker.run(n * args.steps)
            torch_fps.append(T * B / step_s)

        seq_fps, sweep_fps = alternate(args, n, n * T * B * args.steps, one, swept, torch_one_after_another)
        worker.close()
    else:
        seq_fps, sweep_fps = alternate(args, n, n * T * B * args.steps, one, swept)

    ratios = [sw / sq for sq, sw in zip(seq_fps, sweep_fps)]
    r_spread = spread(ratios)
    target = TARGETS.get((args.preset, n))
    result = {
        "benchmark": "sweep_throughput", "variant": args.variant, "preset": args.preset, "conv": args.conv, "configs": n,
        "batch": B, "unroll": T, "steps_per_repeat": args.steps, "repeats": args.repeats, "quick": args.quick,
        "cpu_count": os.cpu_count(), "load_avg_start": load_avg_start,
        "sequential_frames_per_s": float(np.median(seq_fps)), "sweep_frames_per_s": float(np.median(sweep_fps)),
        "sequential_repeats": [round(x, 1) for x in seq_fps], "sweep_repeats": [round(x, 1) for x in sweep_fps],
        "compile_single_s": compile_single, "compile_sweep_s": compile_sweep,
    }
    result["speedup"] = result["sweep_frames_per_s"] / result["sequential_frames_per_s"]
    result.update({
        "ratio_definition": "sweep frames/s / sequential frames/s of the same repeat (measured back to back)",
        "ratio_repeats": [round(x, 4) for x in ratios],
        "ratio_min": r_spread["min"], "ratio_median": r_spread["median"], "ratio_max": r_spread["max"],
        "target": target,
        "target_met": None if target is None else bool(r_spread["median"] >= target),
        "target_met_all_repeats": None if target is None else bool(r_spread["min"] >= target),
        "load_avg_end": os.getloadavg()[0],
    })
    if torch_fps:
        over_torch = [sw / tf for sw, tf in zip(sweep_fps, torch_fps)]
        target_torch = TORCH_TARGETS.get((args.preset, n))
        result["torch"] = {"frames_per_s": float(np.median(torch_fps)), "repeats": [round(x, 1) for x in torch_fps],
                           "ratio_definition": "sweep frames/s / PyTorch's frames/s one after another, same repeat",
                           "sweep_over_torch": spread(over_torch), "target": target_torch,
                           "target_met": None if target_torch is None else bool(spread(over_torch)["median"] >= target_torch)}
    warn_if_busy(result, load_avg_start, result["load_avg_end"])
    verdict = "no target for this N" if target is None else \
        f"target x{target:g} {'met' if result['target_met'] else 'missed'} (median)"
    print(f"{args.variant} {args.preset} N={n} B={B} T={T}: {n} runs one after another "
          f"{result['sequential_frames_per_s']:.0f} frames/s, one vmapped sweep {result['sweep_frames_per_s']:.0f} "
          f"frames/s: x{result['speedup']:.2f}; per-repeat speed-up median x{r_spread['median']:.2f} "
          f"[min {r_spread['min']:.2f}, max {r_spread['max']:.2f}] over {len(ratios)} repeats, {verdict} "
          f"(compile {compile_single:.1f} s single, {compile_sweep:.1f} s sweep; "
          f"load {load_avg_start:.2f} -> {result['load_avg_end']:.2f})")
    if torch_fps:
        t = result["torch"]
        print(f"PyTorch one after another {t['frames_per_s']:.0f} frames/s: sweep / torch "
              f"x{t['sweep_over_torch']['median']:.2f} [min {t['sweep_over_torch']['min']:.2f}, max "
              f"{t['sweep_over_torch']['max']:.2f}]" + ("" if t["target"] is None else
                                                         f", target x{t['target']:g} {'met' if t['target_met'] else 'missed'}"))
    emit(result, args.out)
    return 0


def report_learner(result: dict, load_avg_start: float, out: Path | None) -> int:
    """Print and emit a `--learner` measurement with its per-repeat speed-ups."""
    seq_fps, sweep_fps = result.pop("seq_fps"), result.pop("sweep_fps")
    ratios = [sw / sq for sq, sw in zip(seq_fps, sweep_fps)]
    r_spread = spread(ratios)
    result.update({
        "cpu_count": os.cpu_count(), "load_avg_start": load_avg_start,
        "sequential_frames_per_s": float(np.median(seq_fps)), "sweep_frames_per_s": float(np.median(sweep_fps)),
        "sequential_repeats": [round(x, 1) for x in seq_fps], "sweep_repeats": [round(x, 1) for x in sweep_fps],
        "ratio_definition": "sweep frames/s / sequential frames/s of the same repeat (measured back to back)",
        "ratio_repeats": [round(x, 4) for x in ratios],
        "ratio_min": r_spread["min"], "ratio_median": r_spread["median"], "ratio_max": r_spread["max"],
        "target_met": bool(r_spread["median"] >= result["target"]),
        "target_met_all_repeats": bool(r_spread["min"] >= result["target"]),
        "load_avg_end": os.getloadavg()[0],
    })
    result["speedup"] = result["sweep_frames_per_s"] / result["sequential_frames_per_s"]
    warn_if_busy(result, load_avg_start, result["load_avg_end"])
    print(f"{result['learner']} ({result['variant']}) {result['preset']} N={result['configs']} seeds "
          f"B={result['batch']} T={result['unroll']}: one after another {result['sequential_frames_per_s']:.0f} "
          f"frames/s, one vmapped sweep {result['sweep_frames_per_s']:.0f} frames/s: x{result['speedup']:.2f}; "
          f"per-repeat median x{r_spread['median']:.2f} [min {r_spread['min']:.2f}, max {r_spread['max']:.2f}], "
          f"target x{result['target']:g} {'met' if result['target_met'] else 'missed'} (compile "
          f"{result['compile_single_s']:.1f} s single, {result['compile_sweep_s']:.1f} s sweep, lanes' init "
          f"{result['init_lanes_s']:.1f} s; load {load_avg_start:.2f} -> {result['load_avg_end']:.2f})")
    emit(result, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
