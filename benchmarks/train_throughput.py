"""Training throughput: cdrl's jitted train step against an eager PyTorch reference.

For each variant (`main`, `closed_loop_minus`) and batch size B (1 and 8), one process builds

  * cdrl: `cdrl.training.step.train_step` (jitted, the variant a static argument, the state donated;
    SGD lr 0.1, momentum 0.9 with the divergence monitor and the keep-the-old-state-on-
    divergence selects, exactly what `cdrl train` runs), and
  * torch: `reference/torch_model.py` (eager PyTorch, same network, same loss,
    torch.optim.SGD(lr 0.1, momentum 0.9), the same norm-ratio monitor, carry detached
    between chunks), `torch.set_num_threads(os.cpu_count())`,

from the SAME initial weights, feeds both the same synthetic uint8 chunks of T (`--unroll`)
frames of B streams (random values: the cost does not depend on them), warms up (cdrl: the
first call, which compiles; torch: a few steps), then runs `--repeats` ALTERNATING repeats
(cdrl repeat, torch repeat, ...) of `--steps-per-repeat` steps each. Every step of both reads
its loss back to the host (as a training loop that logs does). Reported per configuration:

  * training frames/s of each (median over the repeats, and every repeat; frames = T * B per
    step) and the ratio cdrl / torch: `ratio_cdrl_over_torch` is the ratio of the two medians;
    `ratio_repeats` is the ratio of each repeat (cdrl's frames/s over torch's, the two measured
    back to back in that repeat) and `ratio_min`, `ratio_median`, `ratio_max` summarise them;
  * `target` (the cdrl / torch speed-up asked for, thesis preset only: 1 for `main` at every B,
    1.5 for `closed_loop_minus` at B 1; null elsewhere) and `target_met`: true only when
    `ratio_median` reaches it (`target_met_all_repeats`: when `ratio_min` does too). The spread is
    printed next to the verdict: a median that meets the target while `ratio_min` does not is
    within the noise;
  * `batching`, per variant, the largest B against the smallest: cdrl's frames/s ratio (target:
    at least 1, batching must not cost speed) and the peak memory growth of both at the larger
    B (target: cdrl's no more than torch's);
  * cdrl's compile time: the first call of the train step (trace + lower + compile + one
    step), with jax's persistent compilation cache disabled for the whole benchmark; one
    measurement per configuration (no spread), against the target of 30 s
    (`compile_target_s`, `compile_target_met`);
  * peak memory of each: the process's peak RSS (VmHWM) during that framework's repeats,
    after resetting it (writing 5 to /proc/self/clear_refs, after a malloc_trim) before each
    repeat; reported as the peak itself and as the growth over the RSS at the reset. This is
    process RSS: the other framework's resident weights and buffers are in the peak (not in
    the growth), and memory that the allocator kept from earlier phases can hide growth, so
    the growth is a lower bound. cdrl's compile is reported separately, and so is the scratch
    memory XLA's compiled train step allocates for each call (`xla_temp_mib`, from
    `memory_analysis()`: the activations kept for the backward pass and the working arrays);
  * model-FLOP utilisation: model FLOPs per step / median step time / matmul peak.
    Model FLOPs are ANALYTIC: the multiply-adds (x2) of every convolution, transposed
    convolution (counted on its un-dilated input), LSTM and FC matmul per frame, times 3 for
    the forward and backward passes (elementwise work not counted). XLA's own count
    (`jax.jit(...).lower(...).compile().cost_analysis()['flops']`) is reported alongside for
    reference only: it counts the body of a `lax.scan` once, not T times (so for
    closed_loop_minus, whose whole network is inside the scan, it is about 1/T of the work)
    and counts the zeros of the dilated input of a transposed convolution. The peak is the
    best of several 2048x2048 float32 matmuls, measured in the same run in jax and in
    torch; MFU uses the larger of the two.

Online training of `final_proposal` (cdrl only: there is NO torch reference for it). One
`cdrl.learners.thesis_ascent.ThesisAscent.train_step`, jitted, is a program that acts in B (= each `--batches` entry)
built-in games (simulated and rendered at 150x150, resized to the preset's image size) for T
steps and learns from them, so its frames/s (frames = num_envs * unroll per update) include
the games and are not comparable with the offline figures (no ratio, so only the spread of its
frames/s over the repeats: `frames_per_s_min`, `frames_per_s_max`, the median being `frames_per_s`). Its compile time (first call) is
reported too (about a minute on 2 cores even for the small preset). `--online-batches` picks
the numbers of games (default: `--batches`; `--quick`: the smallest), `--skip-online` leaves
it out.

malloc: the benchmark re-executes itself under the `cdrl` command's malloc
(`cdrl.runs.allocator`: tcmalloc where installed; the JSON's `malloc`), which torch's
allocations share; `CDRL_MALLOC=system` runs both on glibc's.

Torch threads: `torch.set_num_threads(os.cpu_count())` unless `--torch-threads`. On a machine
that other processes keep busy, torch with as many threads as cores can be many times slower
than with one (its OpenMP threads wait for each other): run on an idle machine, or compare
with `--torch-threads 1`.

Prints a table, then ONE JSON line with every figure (`--out FILE` also writes that line to FILE;
committed results go to benchmarks/results/train_throughput.json). Wall-clock figures depend on
what else runs on the machine: the JSON records the 1-minute load average at the start
(`load_avg_start`) and at the end (`load_avg_end`) and a `warning` when either is above half the
number of CPUs.

    .venv/bin/python benchmarks/train_throughput.py                 # thesis preset
    .venv/bin/python benchmarks/train_throughput.py --quick         # small preset, T=8, B=2, few steps
"""
from __future__ import annotations

import argparse
import ctypes
import dataclasses
import gc
import os
import platform
import statistics
import sys
import time
import types
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from common import emit, spread  # noqa: E402

MiB = 1024 * 1024
# Building the initial weights is set-up, not measured: compile it with LLVM optimisation
# off (the truncated-normal initialisers otherwise take ~30 s to compile on 2 cores).
_FAST_COMPILE = {"xla_backend_optimization_level": 0}
# The cdrl / torch training-throughput targets (README "Against PyTorch"), defined for the
# thesis-sized model: (variant, B) -> minimum ratio, None meaning any B.
TARGETS = {("main", None): 1.0, ("closed_loop_minus", 1): 1.5}
# With oneDNN's convolutions (`--onednn`): cdrl_onednn / torch.
ONEDNN_TARGETS = {("main", None): 1.3, ("closed_loop_minus", None): 1.5}
ONEDNN_GROWTH_TARGET = 0.9  # cdrl_onednn's peak memory growth at the largest B / torch's
TARGET_PRESET = "thesis"
COMPILE_TARGET_S = 30.0


def target_for(preset_name: str, variant: str, batch: int, targets: dict = TARGETS) -> float | None:
    if preset_name != TARGET_PRESET:
        return None
    return targets.get((variant, batch), targets.get((variant, None)))


def ratio_fields(ratios: list[float], target: float | None) -> dict:
    """The per-repeat ratios, their spread and the verdict against `target` (from the median)."""
    s = spread(ratios)
    return {"ratio_repeats": list(ratios), "ratio_min": s["min"], "ratio_median": s["median"],
            "ratio_max": s["max"], "target": target,
            "target_met": None if target is None else bool(s["median"] >= target),
            "target_met_all_repeats": None if target is None else bool(s["min"] >= target)}


def _parse() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--variants", nargs="+", default=["main", "closed_loop_minus"],
                    choices=["main", "closed_loop_minus"])
    ap.add_argument("--batches", type=int, nargs="+", default=None, help="batch sizes B (default 1 8; --quick: 2)")
    ap.add_argument("--preset", default=None, help="architecture preset (default thesis; --quick: small)")
    ap.add_argument("--unroll", type=int, default=None, help="truncated-BPTT length T (default 32; --quick: 8)")
    ap.add_argument("--repeats", type=int, default=None, help="timed repeats per framework (default 5)")
    ap.add_argument("--steps-per-repeat", type=int, default=None, help="train steps per repeat (default 4)")
    ap.add_argument("--torch-warmup", type=int, default=None, help="torch warm-up steps (default 2)")
    ap.add_argument("--matmul-repeats", type=int, default=None, help="matmuls timed for the peak (default 10)")
    ap.add_argument("--torch-threads", type=int, default=None,
                    help="torch.set_num_threads (default os.cpu_count(); on a machine shared with other "
                         "processes fewer threads can be much faster: torch's OpenMP threads wait for each other)")
    ap.add_argument("--quick", action="store_true", help="small preset, few steps (a smoke test)")
    ap.add_argument("--online-batches", type=int, nargs="+", default=None,
                    help="numbers of games for final_proposal's online training (default: --batches; --quick: the smallest of --batches)")
    ap.add_argument("--skip-online", action="store_true", help="leave out final_proposal's online training")
    ap.add_argument("--onednn", action="store_true",
                    help="also train cdrl with oneDNN's convolutions (`--conv onednn`), in the same alternating "
                         "repeats: the JSON's cdrl_onednn beside cdrl (XLA's formulation) and torch")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None, help="also write the JSON to this file")
    args = ap.parse_args()
    quick = args.quick
    defaults = {
        "batches": [2] if quick else [1, 8],
        "preset": "small" if quick else "thesis",
        "repeats": 3 if quick else 5,
        "steps_per_repeat": 2 if quick else 4,
        "torch_warmup": 1 if quick else 2,
        "unroll": 8 if quick else 32,
        "matmul_repeats": 3 if quick else 10,
    }
    for name, value in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    if args.online_batches is None:
        args.online_batches = [min(args.batches)] if quick else list(args.batches)
    return args


# --------------------------------------------------------------------------- memory


_libc = None


def _trim() -> None:
    """Return freed heap memory to the OS so that a phase's growth shows in its peak."""
    global _libc
    gc.collect()
    try:
        if _libc is None:
            _libc = ctypes.CDLL("libc.so.6")
        _libc.malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _status_kib(field: str) -> int | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


class PeakRSS:
    """Peak RSS of a phase: reset VmHWM on entry (Linux clear_refs), read it on exit."""

    def __enter__(self):
        _trim()
        try:
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")
            self.ok = True
        except OSError:
            self.ok = False
        self.start_kib = _status_kib("VmRSS")
        return self

    def __exit__(self, *exc):
        hwm = _status_kib("VmHWM") if self.ok else None
        self.peak_mib = None if hwm is None else hwm * 1024 / MiB
        self.growth_mib = None if hwm is None or self.start_kib is None else (hwm - self.start_kib) * 1024 / MiB
        return False


def _worst(phases: list[PeakRSS]) -> tuple[float | None, float | None]:
    peaks = [p.peak_mib for p in phases if p.peak_mib is not None]
    growths = [p.growth_mib for p in phases if p.growth_mib is not None]
    return (max(peaks) if peaks else None, max(growths) if growths else None)


# --------------------------------------------------------------------------- FLOPs


def forward_flops_per_frame(arch) -> float:
    """Analytic multiply-add FLOPs (x2) of one frame through E_o, LSTM, FC and D_o."""
    flops, size, c_in = 0.0, arch.image_size, 1
    for spec in arch.encoder:
        size = spec.out_size(size)
        flops += 2.0 * size * size * spec.kernel ** 2 * c_in * spec.features
        c_in = spec.features
    chans = [1] + [s.features for s in arch.encoder]
    size = 1
    for i, spec in enumerate(reversed(arch.encoder)):
        c_in, c_out = chans[-1 - i], chans[-2 - i]
        flops += 2.0 * size * size * spec.kernel ** 2 * c_in * c_out  # each input pixel x the kernel
        size = spec.transposed_out_size(size)
    H, code = arch.lstm_size, arch.obs_code
    flops += 2.0 * (code + H) * 4 * H + 2.0 * H * code
    return flops


def matmul_peak(repeats: int, n: int = 2048) -> dict:
    """Best-of-`repeats` GFLOP/s of an n x n float32 matmul in jax and in torch."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    import torch

    rng = np.random.default_rng(0)
    a_np, b_np = (rng.standard_normal((n, n), dtype=np.float32) for _ in range(2))
    flops = 2.0 * n ** 3
    mm = jax.jit(jnp.matmul)
    a, b = jnp.asarray(a_np), jnp.asarray(b_np)
    mm(a, b).block_until_ready()
    best_j = min(_timed(lambda: mm(a, b).block_until_ready()) for _ in range(repeats))
    at, bt = torch.from_numpy(a_np), torch.from_numpy(b_np)
    torch.mm(at, bt)
    best_t = min(_timed(lambda: torch.mm(at, bt)) for _ in range(repeats))
    return {"n": n, "jax_gflops": flops / best_j / 1e9, "torch_gflops": flops / best_t / 1e9}


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


# --------------------------------------------------------------------------- offline training


def _initial_params(variant, seed: int):
    import jax

    key = jax.random.PRNGKey(seed)
    return jax.jit(variant.init).lower(key).compile(compiler_options=_FAST_COMPILE)(key)


def _fresh_state(variant, params, batch: int, hp):
    """What `cdrl.training.step.init_state` builds, from given parameters (copied: the step donates)."""
    import jax
    import jax.numpy as jnp

    from cdrl.training.optim import make_optimizer
    from cdrl.training.step import TrainState

    params = jax.tree.map(jnp.array, params)
    return TrainState(params=params, opt_state=make_optimizer(hp.opt).init(params),
                      carry=variant.init_carry(batch), step=jnp.zeros((), jnp.int32))


def _chunk_arrays(arch, T: int, B: int, seed: int):
    import numpy as np

    rng = np.random.default_rng(seed)
    s = arch.image_size
    frames = rng.integers(0, 256, (T + 1, B, s, s), dtype=np.uint8)
    is_first = np.zeros((T, B), bool)
    is_first[0] = True
    return frames[:-1], frames[1:], is_first


def _torch_serve(conn, arch, name: str, params, arrays, threads: int) -> None:
    """The torch side of `bench_offline` in a process of its own: it builds the reference model
    from `params` and trains it on the chunk `arrays` when asked, `("run", n)` -> (seconds a step,
    peak RSS MiB, growth MiB) of n steps; `("stop", 0)` ends it."""
    import numpy as np
    import torch

    from reference import torch_model as tr

    torch.set_num_threads(threads)
    model = tr.load_cdrl_params(tr.TorchModel(arch, name), params)
    opt = tr.make_optimizer(model, lr=0.1, momentum=0.9)
    obs, next_obs, is_first = (torch.from_numpy(np.array(x)) for x in arrays)
    carry = model.init_carry(obs.shape[1])
    while True:
        cmd, n = conn.recv()
        if cmd == "stop":
            return
        with PeakRSS() as m:
            t0 = time.perf_counter()
            for _ in range(n):
                loss, carry, _ = tr.train_step(model, opt, carry, obs, next_obs, is_first, monitor=True)
                loss.item()
            step_s = (time.perf_counter() - t0) / n
        conn.send((step_s, m.peak_mib, m.growth_mib))


class TorchWorker:
    """PyTorch's reference training in a child process, driven step by step from this one. Apart,
    its OpenMP threads share nothing with oneDNN's (PyTorch and the extension load the same
    libgomp: OpenMP teams started from XLA's threads would make libgomp throttle PyTorch's
    spin-waits, 58 -> 37 frames/s for closed loop - at B 1), and its memory is its own."""

    def __init__(self, arch, name: str, params, arrays, threads: int):
        import multiprocessing

        import jax
        import numpy as np

        ctx = multiprocessing.get_context("spawn")
        self.conn, child = ctx.Pipe()
        params = jax.tree.map(np.asarray, params)
        self.proc = ctx.Process(target=_torch_serve, args=(child, arch, name, params, arrays, threads), daemon=True)
        self.proc.start()

    def run(self, n: int):
        """n train steps: (seconds a step, their memory as a `PeakRSS`-like record)."""
        self.conn.send(("run", n))
        step_s, peak, growth = self.conn.recv()
        return step_s, types.SimpleNamespace(peak_mib=peak, growth_mib=growth)

    def close(self) -> None:
        self.conn.send(("stop", 0))
        self.proc.join(timeout=60)


def bench_offline(name: str, arch, params, T: int, B: int, args) -> dict:
    import jax.numpy as jnp

    from cdrl.data.stream import Chunk
    from cdrl.models import make_variant
    from cdrl.training.optim import HParams
    from cdrl.models import conv
    from cdrl.training.step import train_step

    v = make_variant(name, arch)
    hp = HParams.create(v, lr=0.1, momentum=0.9)
    obs, next_obs, is_first = _chunk_arrays(arch, T, B, args.seed)
    chunk = Chunk(obs=jnp.asarray(obs), next_obs=jnp.asarray(next_obs),
                        action=jnp.zeros((T, B, arch.action_dim), jnp.float32),
                        reward=jnp.zeros((T, B), jnp.float32), is_first=jnp.asarray(is_first))

    # torch in a process of its own (`TorchWorker`): the same weights and chunk.
    torch_worker = TorchWorker(arch, name, params, (obs, next_obs, is_first), args.torch_threads or os.cpu_count())

    # cdrl, each backend its own compiled step (what `cdrl train` runs: the state donated);
    # compile time = lowering, compiling and the first step.
    backends = {"cdrl": "auto", **({"cdrl_onednn": "onednn"} if args.onednn else {})}
    steps, states, compiled_info = {}, {}, {}
    for fw, backend in backends.items():
        variant = make_variant(name, dataclasses.replace(arch, conv=backend))
        state = _fresh_state(variant, params, B, hp)
        with PeakRSS() as compile_mem:
            t0 = time.perf_counter()
            compiled = train_step.lower(variant, state, hp, chunk).compile()
            state, metrics = compiled(state, hp, chunk)
            float(metrics["loss"])
            compile_s = time.perf_counter() - t0
        steps[fw], states[fw] = compiled, state
        cost = compiled.cost_analysis()
        cost = cost[0] if isinstance(cost, (list, tuple)) else cost
        memory = compiled.memory_analysis()
        compiled_info[fw] = {"compile_s": compile_s, "compile_peak_rss_mib": compile_mem.peak_mib,
                             "compile_peak_growth_mib": compile_mem.growth_mib,
                             "xla_temp_mib": memory.temp_size_in_bytes / MiB if memory is not None else None,
                             "conv": conv.formulation(backend),
                             "xla_flops": float(cost.get("flops", float("nan"))) if cost else float("nan")}
    xla_flops = compiled_info["cdrl"]["xla_flops"]

    torch_worker.run(args.torch_warmup)

    frameworks = [*backends, "torch"]
    times = {fw: [] for fw in frameworks}
    mem = {fw: [] for fw in frameworks}
    n = args.steps_per_repeat
    for _ in range(args.repeats):
        for fw in backends:
            with PeakRSS() as m:
                t0 = time.perf_counter()
                for _ in range(n):
                    states[fw], metrics = steps[fw](states[fw], hp, chunk)
                    float(metrics["loss"])
                times[fw].append((time.perf_counter() - t0) / n)
            mem[fw].append(m)
        step_s, m = torch_worker.run(n)
        times["torch"].append(step_s)
        mem["torch"].append(m)
    torch_worker.close()
    if bool(metrics["diverged"]):
        print(f"warning: cdrl step diverged ({name}, B={B}); the timing still holds", file=sys.stderr)

    frames = T * B
    model_flops = 3.0 * forward_flops_per_frame(arch) * frames
    out = {"variant": name, "batch": B, "unroll": T, "frames_per_step": frames,
           "model_flops_per_step": model_flops, "xla_flops_per_step": xla_flops}
    for fw in frameworks:
        step_s = statistics.median(times[fw])
        peak, growth = _worst(mem[fw])
        out[fw] = {
            "frames_per_s": frames / step_s,
            "frames_per_s_repeats": [frames / t for t in times[fw]],
            "step_s": step_s,
            "model_gflops_per_s": model_flops / step_s / 1e9,
            "peak_rss_mib": peak,
            "peak_growth_mib": growth,
        }
    for fw, info in compiled_info.items():
        out[fw].update({k: v for k, v in info.items() if k != "xla_flops"})
        out[fw]["compile_target_s"] = COMPILE_TARGET_S
        out[fw]["compile_target_met"] = bool(info["compile_s"] < COMPILE_TARGET_S) if args.preset == TARGET_PRESET else None
    out["ratio_cdrl_over_torch"] = out["cdrl"]["frames_per_s"] / out["torch"]["frames_per_s"]
    # Repeat i ran cdrl then torch back to back: cdrl frames/s / torch frames/s = torch time / cdrl time.
    per_repeat = lambda fw, ref: [tr_ / tc for tc, tr_ in zip(times[fw], times[ref])]  # noqa: E731
    out.update(ratio_fields(per_repeat("cdrl", "torch"), target_for(args.preset, name, B)))
    if "cdrl_onednn" in backends:
        out["onednn"] = {"over_torch": ratio_fields(per_repeat("cdrl_onednn", "torch"),
                                                    target_for(args.preset, name, B, ONEDNN_TARGETS)),
                         "over_xla": spread(per_repeat("cdrl_onednn", "cdrl"))}
    return out


# --------------------------------------------------------------------------- online training


def bench_online(arch_preset: str, B: int, T: int, args, backend: str = "auto") -> dict:
    import jax

    from cdrl.learners.api import train_program
    from cdrl.models import conv
    from cdrl.runs.config import RunConfig
    from cdrl.runs.online import build_learner

    # The ascent on from the first update: the steady state (before it is on, a step takes one backward pass less).
    cfg = RunConfig(variant="final_proposal", preset=arch_preset, batch=B, unroll=T, seed=args.seed, warmup_steps=0,
                    conv=backend)
    learner = build_learner(cfg)
    state = learner.init(jax.random.PRNGKey(cfg.seed))  # set-up, not measured

    def online_step(state):
        return train_program(learner, state)

    with PeakRSS() as compile_mem:
        t0 = time.perf_counter()
        state, metrics = online_step(state)
        float(metrics["loss"])
        compile_s = time.perf_counter() - t0
    times, mem = [], []
    n = args.steps_per_repeat
    for _ in range(args.repeats):
        with PeakRSS() as m:
            t0 = time.perf_counter()
            for _ in range(n):
                state, metrics = online_step(state)
                float(metrics["loss"])
            times.append((time.perf_counter() - t0) / n)
        mem.append(m)
    frames = B * T
    step_s = statistics.median(times)
    peak, growth = _worst(mem)
    fps = [frames / t for t in times]
    return {"variant": "final_proposal", "conv": conv.formulation(backend), "num_envs": B, "unroll": T, "frames_per_step": frames,
            "frames_per_s": frames / step_s, "frames_per_s_repeats": fps,
            "frames_per_s_min": min(fps), "frames_per_s_max": max(fps),
            "step_s": step_s, "compile_s": compile_s, "compile_peak_rss_mib": compile_mem.peak_mib,
            "peak_rss_mib": peak, "peak_growth_mib": growth}


# --------------------------------------------------------------------------- report


def _fmt(x, spec=".0f"):
    return "-" if x is None else format(x, spec)


def print_table(res: dict) -> None:
    peak = res["matmul_peak_gflops"]
    print(f"preset {res['preset']}, T={res['unroll']}, {res['cpu_count']} CPUs ({res['cpu']}), "
          f"load avg at start {res['load_avg_start']:.2f}, torch threads {res['torch_threads']}")
    if "warning" in res:
        print("WARNING: " + res["warning"])
    print(f"matmul peak 2048x2048 float32: jax {res['matmul']['jax_gflops']:.1f} GFLOP/s, "
          f"torch {res['matmul']['torch_gflops']:.1f} GFLOP/s (MFU against {peak:.1f})")
    head = (f"{'variant':18s} {'B':>3s} {'fw':5s} {'frames/s':>9s} {'ratio':>6s} {'step ms':>9s} "
            f"{'GFLOP/s':>8s} {'MFU':>6s} {'compile s':>9s} {'peak MiB':>9s} {'growth MiB':>10s}")
    print(head)
    print("-" * len(head))
    for r in res["configs"]:
        for fw in ("cdrl", "cdrl_onednn", "torch"):
            if fw not in r:
                continue
            x = r[fw]
            ratio = f"{'':6s}" if fw == "torch" else f"{x['frames_per_s'] / r['torch']['frames_per_s']:6.2f}"
            compile_s = _fmt(x.get("compile_s"), ".1f")
            print(f"{r['variant']:18s} {r['batch']:3d} {fw.replace('cdrl_onednn', 'dnnl'):5s} {x['frames_per_s']:9.1f} {ratio} "
                  f"{1e3 * x['step_s']:9.1f} {x['model_gflops_per_s']:8.2f} {100 * x['mfu']:5.1f}% "
                  f"{compile_s:>9s} {_fmt(x['peak_rss_mib']):>9s} {_fmt(x['peak_growth_mib']):>10s}")
    print("model FLOPs: analytic (convs, transposed convs, LSTM, FC; x3 for training); "
          "XLA cost_analysis flops per step (scan body once): "
          + ", ".join(f"{r['variant']}/B{r['batch']}: {r['xla_flops_per_step'] / 1e9:.2f} G "
                      f"(analytic {r['model_flops_per_step'] / 1e9:.2f} G)" for r in res["configs"]))
    print("cdrl / torch per repeat (the two measured back to back): median [min, max]; a target is met "
          "only when the median meets it")
    for r in res["configs"]:
        if r["target"] is None:
            verdict = f"no target ({'not the ' + TARGET_PRESET + ' preset' if res['preset'] != TARGET_PRESET else 'none for this B'})"
        else:
            verdict = f"target {r['target']:g}: {'met' if r['target_met'] else 'missed'}"
            if r["target_met"] and not r["target_met_all_repeats"]:
                verdict += " (not by every repeat: within the noise)"
            elif not r["target_met"] and r["ratio_max"] >= r["target"]:
                verdict += " (met by some repeats: within the noise)"
        print(f"  {r['variant']:18s} B {r['batch']:3d}: {r['ratio_median']:.3f} [{r['ratio_min']:.3f}, "
              f"{r['ratio_max']:.3f}] over {len(r['ratio_repeats'])} repeats; {verdict}")
        if "onednn" in r:
            o, x = r["onednn"]["over_torch"], r["onednn"]["over_xla"]
            target = "no target" if o["target"] is None else \
                f"target {o['target']:g}: {'met' if o['target_met'] else 'missed'}"
            print(f"  {'  on oneDNN':18s} B {r['batch']:3d}: {o['ratio_median']:.3f} [{o['ratio_min']:.3f}, "
                  f"{o['ratio_max']:.3f}]; {target}; over XLA's formulation {x['median']:.3f} "
                  f"[{x['min']:.3f}, {x['max']:.3f}]")
    for b in res.get("batching", []):
        g = b["peak_growth_mib"]
        print(f"  batching {b['variant']:18s} B {b['batches'][0]} -> {b['batches'][1]}: cdrl frames/s x{b['cdrl_fps_ratio']:.3f} "
              f"(torch x{b['torch_fps_ratio']:.3f}), target >= 1: {'met' if b['fps_target_met'] else 'missed'}; "
              f"memory growth cdrl {_fmt(g['cdrl'])} MiB, torch {_fmt(g['torch'])} MiB: "
              f"{'met' if b['growth_target_met'] else 'missed'}"
              + (f"; on oneDNN {_fmt(g['cdrl_onednn'])} MiB, {b['onednn_growth_over_torch']:.2f} of torch's (target "
                 f"<= {ONEDNN_GROWTH_TARGET:g}): {'met' if b['onednn_growth_target_met'] else 'missed'}"
                 if "onednn_growth_over_torch" in b else ""))
    for r in res.get("online", []):
        print(f"online final_proposal (cdrl only, games included, conv {r['conv']}) num_envs {r['num_envs']:3d}: "
              f"{r['frames_per_s']:9.1f} frames/s [{r['frames_per_s_min']:.1f}, {r['frames_per_s_max']:.1f}], "
              f"step {1e3 * r['step_s']:.1f} ms, compile {r['compile_s']:.1f} s, peak {_fmt(r['peak_rss_mib'])} MiB")
    print(f"load average: {res['load_avg_start']:.2f} at the start, {res['load_avg_end']:.2f} at the end")


def main() -> None:
    from cdrl.runs.allocator import reexec_with_allocator

    reexec_with_allocator()  # malloc as the `cdrl` command has it (CDRL_MALLOC; torch's share it)
    args = _parse()
    import jax

    jax.config.update("jax_enable_compilation_cache", False)  # compile times are real compiles
    import torch

    torch.set_num_threads(args.torch_threads or os.cpu_count())
    from cdrl.models.arch import preset

    arch = preset(args.preset)
    T = args.unroll
    res = {
        "benchmark": "train_throughput", "preset": args.preset, "image_size": arch.image_size,
        "lstm_size": arch.lstm_size, "unroll": T, "batches": args.batches, "repeats": args.repeats,
        "steps_per_repeat": args.steps_per_repeat, "quick": args.quick, "online_batches": args.online_batches,
        "cpu_count": os.cpu_count(), "cpu": _cpu_name(), "torch_threads": torch.get_num_threads(),
        "jax_version": jax.__version__, "torch_version": torch.__version__,
        "jax_device": str(jax.devices()[0].device_kind), "python": platform.python_version(),
        "load_avg_start": os.getloadavg()[0], "persistent_compilation_cache": False,
        "malloc": os.environ.get("CDRL_MALLOC_PRELOADED", "system"),
        "flops_source": "analytic (x3 forward); xla_flops_per_step from compiled cost_analysis, scan body counted once",
        "memory": "process RSS (VmHWM after clear_refs); growth = peak - RSS at reset",
    }
    if res["load_avg_start"] > 0.5 * os.cpu_count():
        res["warning"] = (f"machine busy at start (load average {res['load_avg_start']:.1f} on {os.cpu_count()} CPUs): "
                          f"timings are unreliable, torch with {res['torch_threads']} threads especially")
        print("warning: " + res["warning"], file=sys.stderr, flush=True)
    res["matmul"] = matmul_peak(args.matmul_repeats)
    res["matmul_peak_gflops"] = max(res["matmul"]["jax_gflops"], res["matmul"]["torch_gflops"])

    from cdrl.models import make_variant

    params_by_shape = {}
    res["configs"] = []
    for name in args.variants:
        v = make_variant(name, arch)
        shape_key = str(jax.eval_shape(v.init, jax.random.PRNGKey(args.seed)))
        if shape_key not in params_by_shape:  # main and closed_loop_minus share one parameter tree
            params_by_shape[shape_key] = _initial_params(v, args.seed)
        for B in args.batches:
            r = bench_offline(name, arch, params_by_shape[shape_key], T, B, args)
            for fw in ("cdrl", "cdrl_onednn", "torch"):
                if fw in r:
                    r[fw]["mfu"] = r[fw]["model_gflops_per_s"] / res["matmul_peak_gflops"]
            res["configs"].append(r)
            dnnl = f", cdrl on oneDNN {r['cdrl_onednn']['frames_per_s']:.1f}" if "cdrl_onednn" in r else ""
            print(f"  {name} B={B}: cdrl {r['cdrl']['frames_per_s']:.1f}{dnnl} frames/s, torch "
                  f"{r['torch']['frames_per_s']:.1f} frames/s, cdrl compile {r['cdrl']['compile_s']:.1f} s",
                  file=sys.stderr, flush=True)
    res["online"] = []
    if not args.skip_online:
        for B in args.online_batches:
            for backend in ("auto", "onednn") if args.onednn else ("auto",):
                r = bench_online(args.preset, B, T, args, backend)
                res["online"].append(r)
                print(f"  online final_proposal num_envs={B}, conv {r['conv']}: {r['frames_per_s']:.1f} frames/s, "
                      f"compile {r['compile_s']:.1f} s", file=sys.stderr, flush=True)
    res["load_avg_end"] = os.getloadavg()[0]
    if res["load_avg_end"] > 0.5 * os.cpu_count() and "warning" not in res:
        res["warning"] = (f"machine busy at the end (load average {res['load_avg_end']:.1f} on {os.cpu_count()} CPUs): "
                          f"timings are unreliable")
        print("warning: " + res["warning"], file=sys.stderr, flush=True)
    res["targets"] = {"preset": TARGET_PRESET, "cdrl_over_torch": {f"{v}/B{'any' if b is None else b}": t
                                                                   for (v, b), t in TARGETS.items()},
                      "cdrl_onednn_over_torch": {f"{v}/B{'any' if b is None else b}": t
                                                 for (v, b), t in ONEDNN_TARGETS.items()},
                      "onednn_growth_over_torch_below": ONEDNN_GROWTH_TARGET,
                      "compile_s_below": COMPILE_TARGET_S, "verdict_from": "ratio_median"}
    res["batching"] = batching(res["configs"])
    print_table(res)
    emit(_rounded(res), args.out)


def batching(configs: list[dict]) -> list[dict]:
    """Per variant, the largest batch against the smallest: cdrl's frames/s must not fall
    (`fps_ratio` >= 1) and cdrl's peak memory growth must be no more than torch's at the
    larger batch (`growth_target_met`); thesis preset targets, judged on the medians."""
    out = []
    for name in dict.fromkeys(r["variant"] for r in configs):
        rows = sorted((r for r in configs if r["variant"] == name), key=lambda r: r["batch"])
        if len(rows) < 2:
            continue
        lo, hi = rows[0], rows[-1]
        fps_ratio = hi["cdrl"]["frames_per_s"] / lo["cdrl"]["frames_per_s"]
        growth = {fw: hi[fw]["peak_growth_mib"] for fw in ("cdrl", "cdrl_onednn", "torch") if fw in hi}
        row = {"variant": name, "batches": [lo["batch"], hi["batch"]], "cdrl_fps_ratio": fps_ratio,
               "torch_fps_ratio": hi["torch"]["frames_per_s"] / lo["torch"]["frames_per_s"],
               "fps_target_met": bool(fps_ratio >= 1.0), "peak_growth_mib": growth,
               "growth_target_met": None if None in growth.values() else bool(growth["cdrl"] <= growth["torch"])}
        if "cdrl_onednn" in growth and None not in growth.values():
            row["onednn_growth_over_torch"] = growth["cdrl_onednn"] / growth["torch"]
            row["onednn_growth_target_met"] = bool(row["onednn_growth_over_torch"] <= ONEDNN_GROWTH_TARGET)
        out.append(row)
    return out


def _cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _rounded(x):
    if isinstance(x, float):
        return float(f"{x:.4g}")
    if isinstance(x, dict):
        return {k: _rounded(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_rounded(v) for v in x]
    return x


if __name__ == "__main__":
    main()
