"""Scaling of a sweep over devices and processes: configurations/s and frames/s of the same
sweep program (`cdrl.runs.grid.run_grid`: the data streams, the sharded step, the host loop)
on three layouts of CPU cores, each a fresh set of processes pinned with `taskset`:

  * `1proc_1core`: one process on core 0, one device, K configurations;
  * `2proc_1core`: two processes joined by `jax.distributed` on localhost, pinned to cores 0
    and 1, one device each, 2K configurations (the config axis sharded over both);
  * `1proc_2core`: one process on cores 0 and 1 with two host devices
    (`--xla_force_host_platform_device_count=2`), 2K configurations.

Every process runs XLA single-threaded (`--xla_cpu_multi_thread_eigen=false`), so a layout
uses exactly the cores it is pinned to. Weak
scaling: each device holds K configurations, so ideal scaling doubles the configurations/s
(configuration-steps per second; frames/s is that times B x T). After `--warmup` steps (the
compile), `--repeats` consecutive windows of `--steps` steps are timed, each window from the
end of one step's host work to the end of another's; with two processes a window's time is
the slower process's. Reported per layout: configurations/s and frames/s, min / median / max
over the windows; `speedup` (median over `1proc_1core`'s median), `efficiency` (speedup / 2)
and the target (two processes on one core each >= 1.8x one process on one core), met on the
medians (`target_met`) and on the worst windows (`target_met_all_repeats`: the slowest
two-process window against the fastest one-process window); the load average before and
after. One JSON line at the end (`--out FILE` also writes it there).

    .venv/bin/python benchmarks/scaling.py --out benchmarks/results/scaling.json   # small preset
    .venv/bin/python benchmarks/scaling.py --quick                                  # tiny: does it run
    .venv/bin/python benchmarks/scaling.py --conv onednn                            # oneDNN's convolutions
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np

from common import emit, spread, warn_if_busy

ROOT = Path(__file__).resolve().parent.parent
SINGLE_THREAD = "--xla_cpu_multi_thread_eigen=false"  # (`intra_op_parallelism_threads=1` is no XLA flag: it ends the parsing of XLA_FLAGS)
TARGET = 1.8
LAYOUTS = {  # name -> (processes, cores of each process, host devices per process)
    "1proc_1core": (1, ["0"], 1),
    "2proc_1core": (2, ["0", "1"], 1),
    "1proc_2core": (1, ["0,1"], 2),
}


def worker(setup: dict) -> None:
    """One process of a layout: the sweep program, timed in windows; process 0 prints them."""
    if setup["processes"] > 1:
        from cdrl.runs.distributed import initialize

        initialize()
    import jax

    from cdrl.data.synthetic import synthetic_episodes
    from cdrl.models import make_variant
    from cdrl.runs.config import RunConfig
    from cdrl.runs.distributed import allgather_json
    from cdrl.runs.grid import Grid, held_configs, make_streams, run_grid
    from cdrl.training.parallel import ConfigAxis

    count = setup["per_device"] * jax.device_count()
    base = RunConfig(variant="main", preset=setup["preset"], batch=setup["batch"], unroll=setup["unroll"],
                     conv=setup["conv"], tensorboard=False)
    cfgs = Grid(lr=tuple(0.1 / 2 ** i for i in range(count))).configs(base)
    axis = ConfigAxis.create(0, len(cfgs))
    episodes = synthetic_episodes(2 * setup["batch"], 4 * setup["unroll"] + 1, base.arch.image_size)
    streams = make_streams(held_configs(cfgs, axis), lambda c: episodes)
    result = run_grid(make_variant("main", base.arch), cfgs, streams,
                      setup["warmup"] + setup["repeats"] * setup["steps"], axis=axis)
    stamps = np.cumsum(result.seconds)  # the end of every step, from the loop's start
    ends = stamps[setup["warmup"] - 1::setup["steps"]]
    windows = np.diff(ends).tolist()
    slowest = np.max(allgather_json(windows), axis=0).tolist()
    if jax.process_index() == 0:
        print("RESULT " + json.dumps({"configs": len(cfgs), "devices": jax.device_count(), "windows_s": slowest}),
              flush=True)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def run_layout(name: str, setup: dict) -> dict:
    processes, cores, devices = LAYOUTS[name]
    port = _free_port()
    procs = []
    for i in range(processes):
        env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT),
               "XLA_FLAGS": f"{SINGLE_THREAD} --xla_force_host_platform_device_count={devices}"}
        if processes > 1:
            env.update(JAX_COORDINATOR_ADDRESS=f"localhost:{port}", JAX_NUM_PROCESSES=str(processes),
                       JAX_PROCESS_ID=str(i))
        cmd = ["taskset", "-c", cores[i], sys.executable, __file__, "--worker",
               json.dumps({**setup, "processes": processes})]
        procs.append(subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    outs = [p.communicate() for p in procs]
    for p, (_, err) in zip(procs, outs):
        if p.returncode != 0:
            raise RuntimeError(f"layout {name}: a process failed:\n{err[-3000:]}")
    result = json.loads(next(line for line in outs[0][0].splitlines() if line.startswith("RESULT "))[7:])
    frames = setup["batch"] * setup["unroll"]
    cps = [result["configs"] * setup["steps"] / s for s in result["windows_s"]]
    return {"processes": processes, "cores": len(",".join(cores).split(",")), "devices": result["devices"],
            "configs": result["configs"], "configs_per_s": spread(cps),
            "frames_per_s": spread([c * frames for c in cps]), "configs_per_s_repeats": [round(c, 2) for c in cps]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default=None, help="architecture preset (default: small; --quick: tiny)")
    parser.add_argument("--per-device", type=int, default=None, help="configurations per device K (default: 4; --quick: 2)")
    parser.add_argument("--batch", type=int, default=None, help="streams per configuration B (default: 4; --quick: 2)")
    parser.add_argument("--unroll", type=int, default=None, help="T (default: 16; --quick: 4)")
    parser.add_argument("--warmup", type=int, default=None, help="untimed steps, the compile (default: 3; --quick: 2)")
    parser.add_argument("--steps", type=int, default=None, help="steps per timed window (default: 10; --quick: 2)")
    parser.add_argument("--repeats", type=int, default=None, help="timed windows per layout (default: 5; --quick: 2)")
    parser.add_argument("--conv", default=None, help="how the convolutions are computed (default: auto)")
    parser.add_argument("--quick", action="store_true", help="a smoke test: tiny preset, a few steps")
    parser.add_argument("--out", type=Path, default=None, help="also write the final JSON line to this file")
    parser.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        worker(json.loads(args.worker))
        return 0
    defaults = ({"preset": "tiny", "per_device": 2, "batch": 2, "unroll": 4, "warmup": 2, "steps": 2, "repeats": 2}
                if args.quick else
                {"preset": "small", "per_device": 4, "batch": 4, "unroll": 16, "warmup": 3, "steps": 10, "repeats": 5})
    defaults["conv"] = "auto"
    setup = {k: getattr(args, k) if getattr(args, k) is not None else v for k, v in defaults.items()}
    if (os.cpu_count() or 1) < 2:
        raise SystemExit("scaling needs at least 2 CPU cores")
    load_avg_start = os.getloadavg()[0]
    layouts = {name: run_layout(name, setup) for name in LAYOUTS}
    one = layouts["1proc_1core"]["configs_per_s"]
    result = {"benchmark": "scaling", "variant": "main", **setup, "quick": args.quick, "cpu_count": os.cpu_count(),
              "xla_flags": SINGLE_THREAD, "load_avg_start": load_avg_start, "layouts": layouts}
    for name in ("2proc_1core", "1proc_2core"):
        speedup = layouts[name]["configs_per_s"]["median"] / one["median"]
        result[f"speedup_{name}"] = speedup
        result[f"efficiency_{name}"] = speedup / 2
    result.update({
        "target": f"2proc_1core configurations/s >= {TARGET}x 1proc_1core's",
        "target_met": bool(result["speedup_2proc_1core"] >= TARGET),
        "target_met_all_repeats": bool(layouts["2proc_1core"]["configs_per_s"]["min"] >= TARGET * one["max"]),
        "load_avg_end": os.getloadavg()[0],
    })
    warn_if_busy(result, load_avg_start, result["load_avg_end"])
    for name, r in layouts.items():
        c = r["configs_per_s"]
        print(f"{name}: {r['configs']} configs on {r['devices']} device(s), {r['processes']} process(es), "
              f"{r['cores']} core(s): {c['median']:.2f} configs/s [min {c['min']:.2f}, max {c['max']:.2f}], "
              f"{r['frames_per_s']['median']:.0f} frames/s")
    print(f"speed-up 2 processes x 1 core: x{result['speedup_2proc_1core']:.2f} (efficiency "
          f"{result['efficiency_2proc_1core']:.0%}), 1 process x 2 cores: x{result['speedup_1proc_2core']:.2f}; "
          f"target x{TARGET} {'met' if result['target_met'] else 'missed'} (median); "
          f"load {load_avg_start:.2f} -> {result['load_avg_end']:.2f}")
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
