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

``--single-thread`` keeps XLA from splitting single operations over cores (which
costs more than it gains when the cores are busy; with ``--procs 2`` it gives each
process its own core).

Wall-clock figures depend on what else runs on the machine; the "obs per
CPU-second" figures (observations / CPU time of the process) are less sensitive to
other processes.

Prints one line per figure, then one JSON line with all figures.

    python benchmarks/env_throughput.py [--quick] [--procs 2] [--single-thread]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _parse() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer batch sizes, short timing")
    ap.add_argument("--batch-sizes", type=int, nargs="*", default=None)
    ap.add_argument("--steps", type=int, default=64, help="steps per scanned call")
    ap.add_argument("--seconds", type=float, default=None, help="timing window per figure")
    ap.add_argument("--procs", type=int, default=1, help="also run this many processes at once")
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


def _measure(policy_name: str, steps: int, batch: int, seconds: float, seed: int = 0,
             barrier=None) -> dict:
    """Observations per second (wall and CPU) of the jitted rollout at one batch size."""
    import jax

    start, rollout = _make_rollout(policy_name, steps)
    carry = start(jax.random.split(jax.random.PRNGKey(seed), batch))
    t0 = time.perf_counter()
    carry, frames = rollout(carry)
    frames.block_until_ready()
    first = time.perf_counter() - t0
    carry, frames = rollout(carry)
    frames.block_until_ready()
    if barrier is not None:
        barrier.wait()
    n = 0
    t0, c0 = time.perf_counter(), time.process_time()
    while time.perf_counter() - t0 < seconds:
        carry, frames = rollout(carry)
        frames.block_until_ready()
        n += batch * steps
    wall = time.perf_counter() - t0
    return {"obs_per_s": n / wall, "obs_per_cpu_s": n / max(time.process_time() - c0, 1e-9),
            "first_call_s": first}


def _worker(args, queue):
    sys.path.insert(0, ROOT)
    queue.put(_measure(*args))


def _measure_procs(procs: int, policy_name: str, steps: int, batch: int, seconds: float) -> float:
    ctx = mp.get_context("spawn")
    barrier = ctx.Barrier(procs)
    queue = ctx.Queue()
    workers = [
        ctx.Process(target=_worker, args=((policy_name, steps, batch, seconds, i, barrier), queue))
        for i in range(procs)
    ]
    for w in workers:
        w.start()
    results = [queue.get() for _ in workers]
    for w in workers:
        w.join()
    return sum(r["obs_per_s"] for r in results)


def _measure_gym(seconds: float) -> float:
    import numpy as np

    from envs.gym_env import SlitherEnv

    env = SlitherEnv()
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(20):
        env.step(rng.uniform(size=3).astype(np.float32))
    n = 0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        _, _, terminated, truncated, _ = env.step(rng.uniform(size=3).astype(np.float32))
        if terminated or truncated:
            env.reset()
        n += 1
    return n / (time.perf_counter() - t0)


def main() -> None:
    args = _parse()
    if args.single_thread:
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_multi_thread_eigen=false").strip()
    sys.path.insert(0, ROOT)
    batch_sizes = args.batch_sizes or ([1, 16, 64] if args.quick else [1, 16, 64, 256])
    seconds = args.seconds or (1.0 if args.quick else 3.0)
    results: dict[str, float] = {}
    for b in batch_sizes:
        r = _measure(args.policy, args.steps, b, seconds)
        results[f"jax_batch{b}_obs_per_s"] = round(r["obs_per_s"], 1)
        results[f"jax_batch{b}_obs_per_cpu_s"] = round(r["obs_per_cpu_s"], 1)
        print(
            f"jax vmap batch {b:4d}: {r['obs_per_s']:10.0f} obs/s  "
            f"{r['obs_per_cpu_s']:10.0f} obs per CPU-second  (first call {r['first_call_s']:.1f} s)",
            flush=True,
        )
    if args.procs > 1:
        for b in batch_sizes:
            if b < 8:
                continue
            rate = _measure_procs(args.procs, args.policy, args.steps, b, seconds)
            results[f"jax_batch{b}_x{args.procs}procs_obs_per_s"] = round(rate, 1)
            print(f"jax vmap batch {b:4d} x {args.procs} processes: {rate:10.0f} obs/s", flush=True)
    gym_rate = _measure_gym(seconds)
    results["gym_single_obs_per_s"] = round(gym_rate, 1)
    print(f"gymnasium SlitherEnv.step: {gym_rate:10.0f} obs/s", flush=True)
    results["jax_best_obs_per_s"] = max(
        (v for k, v in results.items() if k.startswith("jax_") and k.endswith("_obs_per_s")), default=0.0
    )
    results["xla_flags"] = os.environ.get("XLA_FLAGS", "")
    results["cpu_count"] = os.cpu_count()
    results["load_avg_1min"] = round(os.getloadavg()[0], 2)
    results["steps_per_call"] = args.steps
    print(json.dumps(results))


if __name__ == "__main__":
    main()
