"""Throughput of the Slither game: 150 x 150 observations per second.

Measures
  * the vmapped JAX game: ``jit(scan over --steps steps of vmap(policy + step +
    render))`` at several batch sizes, frames returned as uint8 [steps, batch, 150,
    150] (as a data set stores them), games continuing from call to call, after a
    warm-up call;
  * with ``--procs N`` (N > 1), the same at the chosen batch sizes run by N
    processes at once (XLA runs one such program on one core, so this is how a
    data collection uses several cores); the figure is the sum of their rates;
  * the gymnasium wrapper stepping one game (``SlitherEnv.step``).

With ``--devices N`` the one process holds N CPU devices and each batch of games is spread
over them (the batch axis sharded, as ``cdrl collect --devices N`` does): XLA runs each
device's block on its own core, where one device's program keeps the cores busy only part
of the time.

With ``--baseline DIR`` (a checkout of another commit, e.g. ``git worktree add /tmp/base
HEAD~1``), the game of DIR and this tree's game run the same rollout at the chosen batch sizes in
two processes, one timing window at a time, alternating: ``speedup_batch{B}`` is the median
[min, max] of the per-repeat ratios (this tree / DIR), so both commits are measured in one run,
under the same load.

``--single-thread`` keeps XLA from splitting single operations over cores (which
costs more than it gains when the cores are busy; with ``--procs 2`` it gives each
process its own core).

Each figure is timed ``--repeats`` times (windows of ``--seconds`` each; the repeats
of the batch sizes interleaved, so a change of load hits all of them). There is no
paired reference to take a ratio against, so each figure is reported as the median
over its repeats (the flat ``jax_batch{B}_obs_per_s``-style keys, as before) with
its spread under ``spread`` (``{figure: {"repeats": [...], "min", "median",
"max"}}``). ``jax_best_obs_per_s`` is the jax figure with the highest median
(``jax_best_figure`` names it; ``jax_best_obs_per_s_min`` / ``_max`` its spread);
``target_obs_per_s`` is 20,000 and ``target_met`` is true only when that median
reaches it (``target_met_all_repeats`` when its minimum does too).

Wall-clock figures depend on what else runs on the machine; the "obs per
CPU-second" figures (observations / CPU time of the process) are less sensitive to
other processes. The JSON records the 1-minute load average at the start
(``load_avg_start``) and at the end (``load_avg_end``; ``load_avg_1min`` is the same,
kept for older readers) and a ``warning`` when either is above half the CPUs.

Prints one line per figure, then one JSON line with all figures (``--out FILE``
also writes that line to FILE; committed results go to
benchmarks/results/env_throughput.json).

    python benchmarks/env_throughput.py [--quick] [--procs 2] [--single-thread] [--devices N] [--baseline DIR] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
import time

from common import alternate_windows, checkout_commit, recv_or_fail, warn_if_busy

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _parse() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer batch sizes, short timing")
    ap.add_argument("--batch-sizes", type=int, nargs="*", default=None)
    ap.add_argument("--steps", type=int, default=64, help="steps per scanned call")
    ap.add_argument("--seconds", type=float, default=None,
                    help="timing window per figure and repeat (default 3; --quick: 1)")
    ap.add_argument("--repeats", type=int, default=None, help="timed windows per figure (default 5; --quick: 3)")
    ap.add_argument("--out", default=None, help="also write the final JSON line to this file")
    ap.add_argument("--procs", type=int, default=1, help="also run this many processes at once")
    ap.add_argument("--devices", type=int, default=1,
                    help="spread each batch of games over this many CPU devices of the one process (its batch "
                         "sizes multiples of it; the baseline of --baseline runs on one)")
    ap.add_argument("--baseline", default=None, metavar="DIR",
                    help="also time the game of another checkout, alternating windows with this tree's")
    ap.add_argument("--policy", default="uniform", choices=["uniform", "behaviour"])
    ap.add_argument("--single-thread", action="store_true",
                    help="XLA_FLAGS=--xla_cpu_multi_thread_eigen=false (one core per process)")
    return ap.parse_args()


def _make_rollout(policy_name: str, steps: int):
    """(start, rollout): jitted start of a batch of games and a jitted scan of
    ``steps`` steps of all of them returning uint8 frames [steps, batch, 150, 150]."""
    import jax
    import jax.numpy as jnp

    from envs import fastrng
    from envs.gym_env import game_for
    from envs.policies import get_policy

    game = game_for()
    params = game.default_params
    policy = get_policy(policy_name)

    def start(key):
        k_reset, k_pol, k_run = fastrng.split(key, 3)
        state = game.reset_state(k_reset, params)
        return state, policy.init(k_pol), game.get_obs(state, params), k_run

    def one_step(carry):
        state, pstate, obs, key = carry
        key, k_a, k_s = fastrng.split(key, 3)
        action, pstate = policy.step(k_a, pstate, obs)
        state, _, _, _, _ = game.step_state(k_s, state, action, params)
        obs = game.get_obs(state, params)
        return (state, pstate, obs, key), jnp.round(obs * 255.0).astype(jnp.uint8)

    def rollout(carry):
        return jax.lax.scan(lambda c, _: jax.vmap(one_step)(c), carry, None, length=steps)

    return jax.jit(jax.vmap(start)), jax.jit(rollout)


class _Rollout:
    """The jitted rollout at one batch size, compiled and warmed up, games carried on."""

    def __init__(self, policy_name: str, steps: int, batch: int, seed: int = 0, devices: int = 1):
        import jax

        start, self.rollout = _make_rollout(policy_name, steps)
        keys = jax.random.split(jax.random.PRNGKey(seed), batch)
        if devices > 1:  # the games' batch axis over the devices (as `cdrl collect --devices`)
            import numpy as np
            from jax.sharding import Mesh, NamedSharding, PartitionSpec

            mesh = Mesh(np.array(jax.local_devices()[:devices]), ("games",))
            keys = jax.device_put(keys, NamedSharding(mesh, PartitionSpec("games")))
        self.carry = start(keys)
        self.obs_per_call = batch * steps
        t0 = time.perf_counter()
        self._call()
        self.first_call_s = time.perf_counter() - t0
        self._call()

    def _call(self):
        self.carry, frames = self.rollout(self.carry)
        frames.block_until_ready()

    def window(self, seconds: float) -> dict:
        """Observations per second (wall and CPU) over one timing window."""
        n = 0
        t0, c0 = time.perf_counter(), time.process_time()
        while time.perf_counter() - t0 < seconds:
            self._call()
            n += self.obs_per_call
        wall = time.perf_counter() - t0
        return {"obs_per_s": n / wall, "obs_per_cpu_s": n / max(time.process_time() - c0, 1e-9)}


def _worker(args, barrier, queue):
    sys.path.insert(0, ROOT)
    policy_name, steps, batch, seconds, repeats, seed = args
    r = _Rollout(policy_name, steps, batch, seed)
    rates = []
    for _ in range(repeats):
        barrier.wait()  # every process times the same window
        rates.append(r.window(seconds)["obs_per_s"])
    queue.put(rates)


def _measure_procs(procs: int, policy_name: str, steps: int, batch: int, seconds: float, repeats: int) -> list[float]:
    """Per repeat, the summed observations/s of `procs` processes running at once."""
    ctx = mp.get_context("spawn")
    barrier = ctx.Barrier(procs)
    queue = ctx.Queue()
    workers = [
        ctx.Process(target=_worker, args=((policy_name, steps, batch, seconds, repeats, i), barrier, queue))
        for i in range(procs)
    ]
    for w in workers:
        w.start()
    results = [queue.get() for _ in workers]
    for w in workers:
        w.join()
    return [sum(rates) for rates in zip(*results)]


def _paired_worker(root, policy_name, steps, batch, devices, conn):
    """Serves timing windows of one checkout's game: answers each ``seconds`` received on
    ``conn`` with the window's observations/s, until it receives None."""
    sys.path.insert(0, root)
    _use_cpu_devices(devices)
    import envs

    if not os.path.abspath(envs.__file__).startswith(os.path.abspath(root) + os.sep):
        raise RuntimeError(f"the game imported from {envs.__file__}, not from {root}")
    r = _Rollout(policy_name, steps, batch, devices=devices)
    conn.send(r.first_call_s)
    while (seconds := conn.recv()) is not None:
        conn.send(r.window(seconds)["obs_per_s"])


def _measure_against(baseline: str, policy_name: str, steps: int, batch: int, seconds: float,
                     repeats: int, devices: int) -> tuple[list[float], list[float]]:
    """Observations/s per repeat of (this tree's game on ``devices`` devices, the baseline
    checkout's game on one), their windows alternating (which goes first alternates too)."""
    ctx = mp.get_context("spawn")
    pipes, workers = [], []
    for root, count in ((ROOT, devices), (os.path.abspath(baseline), 1)):
        mine, theirs = ctx.Pipe()
        w = ctx.Process(target=_paired_worker, args=(root, policy_name, steps, batch, count, theirs))
        w.start()
        pipes.append(mine)
        workers.append(w)
        recv_or_fail(mine, w)  # compiled and warm; the other compiles after, on an idle machine
    rates = alternate_windows(pipes, workers, seconds, repeats)
    return rates[0], rates[1]


def _use_cpu_devices(count: int) -> None:
    """Ask JAX (not started yet) for ``count`` CPU devices in this process."""
    if count > 1:
        import jax

        jax.config.update("jax_num_cpu_devices", count)


def _measure_gym(seconds: float, repeats: int) -> list[float]:
    import numpy as np

    from envs.gym_env import SlitherEnv

    env = SlitherEnv()
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(20):
        env.step(rng.uniform(size=3).astype(np.float32))
    rates = []
    for _ in range(repeats):
        n = 0
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            _, _, terminated, truncated, _ = env.step(rng.uniform(size=3).astype(np.float32))
            if terminated or truncated:
                env.reset()
            n += 1
        rates.append(n / (time.perf_counter() - t0))
    return rates


TARGET_OBS_PER_S = 20_000.0  # README "Performance"


def _spread(values: list[float]) -> dict:
    import statistics

    d = 1 if max(values) >= 100 else 3  # rates to 0.1 obs/s, ratios to 0.001
    return {"repeats": [round(v, d) for v in values], "min": round(min(values), d),
            "median": round(statistics.median(values), d), "max": round(max(values), d)}


def main() -> None:
    args = _parse()
    load_avg_start = os.getloadavg()[0]
    if args.single_thread:
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_multi_thread_eigen=false").strip()
    sys.path.insert(0, ROOT)
    _use_cpu_devices(args.devices)
    batch_sizes = args.batch_sizes or ([1, 16, 64] if args.quick else [1, 16, 64, 256])
    seconds = args.seconds or (1.0 if args.quick else 3.0)
    repeats = args.repeats or (3 if args.quick else 5)
    results: dict = {}
    spread: dict[str, dict] = {}

    def record(key: str, values: list[float]) -> dict:
        spread[key] = _spread(values)
        results[key] = spread[key]["median"]
        return spread[key]

    rollouts = {}
    for b in batch_sizes:
        rollouts[b] = _Rollout(args.policy, args.steps, b, devices=args.devices)
        print(f"jax vmap batch {b:4d}: first call {rollouts[b].first_call_s:.1f} s", flush=True)
    windows: dict[int, list[dict]] = {b: [] for b in batch_sizes}
    for _ in range(repeats):
        for b in batch_sizes:
            windows[b].append(rollouts[b].window(seconds))
    del rollouts
    for b in batch_sizes:
        w = record(f"jax_batch{b}_obs_per_s", [x["obs_per_s"] for x in windows[b]])
        c = record(f"jax_batch{b}_obs_per_cpu_s", [x["obs_per_cpu_s"] for x in windows[b]])
        print(
            f"jax vmap batch {b:4d}: {w['median']:10.0f} obs/s [{w['min']:.0f}, {w['max']:.0f}]  "
            f"{c['median']:10.0f} obs per CPU-second [{c['min']:.0f}, {c['max']:.0f}]  "
            f"(median [min, max] over {repeats} repeats)",
            flush=True,
        )
    if args.procs > 1:
        for b in batch_sizes:
            if b < 8:
                continue
            rates = _measure_procs(args.procs, args.policy, args.steps, b, seconds, repeats)
            w = record(f"jax_batch{b}_x{args.procs}procs_obs_per_s", rates)
            print(f"jax vmap batch {b:4d} x {args.procs} processes: {w['median']:10.0f} obs/s "
                  f"[{w['min']:.0f}, {w['max']:.0f}]", flush=True)
    if args.baseline:
        results["baseline"] = os.path.abspath(args.baseline)
        results["commit"], results["baseline_commit"] = checkout_commit(ROOT), checkout_commit(args.baseline)
        for b in batch_sizes:
            mine, base = _measure_against(args.baseline, args.policy, args.steps, b, seconds, repeats, args.devices)
            record(f"paired_batch{b}_obs_per_s", mine)
            record(f"baseline_batch{b}_obs_per_s", base)
            w = record(f"speedup_batch{b}", [m / max(o, 1e-9) for m, o in zip(mine, base)])
            print(f"batch {b:4d}, this tree / {args.baseline}: {w['median']:.2f}x [{w['min']:.2f}, {w['max']:.2f}] "
                  f"({results[f'paired_batch{b}_obs_per_s']:.0f} against {results[f'baseline_batch{b}_obs_per_s']:.0f} obs/s)",
                  flush=True)
    w = record("gym_single_obs_per_s", _measure_gym(seconds, repeats))
    print(f"gymnasium SlitherEnv.step: {w['median']:10.0f} obs/s [{w['min']:.0f}, {w['max']:.0f}]", flush=True)
    wall_keys = [k for k in spread if k.startswith("jax_") and k.endswith("_obs_per_s")]
    best = max(wall_keys, key=lambda k: spread[k]["median"]) if wall_keys else None
    results["jax_best_figure"] = best
    results["jax_best_obs_per_s"] = spread[best]["median"] if best else 0.0
    results["jax_best_obs_per_s_min"] = spread[best]["min"] if best else None
    results["jax_best_obs_per_s_max"] = spread[best]["max"] if best else None
    results["target_obs_per_s"] = TARGET_OBS_PER_S
    results["target_met"] = bool(best) and spread[best]["median"] >= TARGET_OBS_PER_S
    results["target_met_all_repeats"] = bool(best) and spread[best]["min"] >= TARGET_OBS_PER_S
    results["spread"] = spread
    results["repeats"] = repeats
    results["seconds_per_repeat"] = seconds
    results["xla_flags"] = os.environ.get("XLA_FLAGS", "")
    results["cpu_count"] = os.cpu_count()
    results["load_avg_start"] = round(load_avg_start, 2)
    results["load_avg_end"] = round(os.getloadavg()[0], 2)
    results["load_avg_1min"] = results["load_avg_end"]
    results["steps_per_call"] = args.steps
    results["devices"] = args.devices
    warn_if_busy(results, results["load_avg_start"], results["load_avg_end"])
    if best:
        print(f"best: {best} median {spread[best]['median']:.0f} obs/s [min {spread[best]['min']:.0f}, max "
              f"{spread[best]['max']:.0f}]: target {TARGET_OBS_PER_S:.0f} obs/s "
              f"{'met' if results['target_met'] else 'missed'} (by the median"
              f"{'; not by every repeat: within the noise' if results['target_met'] and not results['target_met_all_repeats'] else ''}"
              f"{'; met by some repeats: within the noise' if not results['target_met'] and spread[best]['max'] >= TARGET_OBS_PER_S else ''})",
              flush=True)
    print(f"load average: {results['load_avg_start']:.2f} at the start, {results['load_avg_end']:.2f} at the end", flush=True)
    line = json.dumps(results)
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            f.write(line + "\n")
    print(line)


if __name__ == "__main__":
    main()
