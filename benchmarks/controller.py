"""The controller experiment: train controller variants online against the built-in game and
compare their noise-free play with the thesis's two data policies on the same held-out seeds.

Configurations (each `cdrl train` with the same budget), each trained once per seed (`--seeds`,
default 0 1 2; a seed sets the initialisation, the exploration noise and the training games):
  final_proposal, scope controller  (reward ascent moves only the controller D_a)
  final_proposal, scope all         (the thesis's literal wording)
  reward_prediction, scope controller (open loop on observations: does closed loop − help?)
  action_loop                        (no reward head: no ascent; BCE only)

Every run is evaluated on the same held-out games (seeds 10000, 10001, ...), as are the
uniform-random and behaviour-switching policies (identical for every run: they do not learn).

Reported per configuration (`runs[name]`):
  * `seeds[seed]`: that run's `controller` row (`mean_return` over the held-out games, `ci95`:
    the within-run 95 % CI over those games, Student t, `episodes`, `mean_length`) and the mean
    predicted vs real reward per step over the last quarter of training (is reward
    hallucinated?), the final observation BCE, the first / last training returns and the run's
    wall time (`wall_s`, compiles included; later seeds reuse the compiled programs);
  * `per_seed_mean_return`: the per-seed mean returns, in `seeds_order`;
  * `mean_return`, `std_across_seeds` (ddof 1) and `ci95_across_seeds`: the 95 % CI of the mean
    over seeds, Student t with n - 1 degrees of freedom (null with one seed; with 3 seeds t is
    4.30, so the interval is wide: it is the honest one);
  * the same three for the predicted and the real reward per step (`predicted_reward_per_step`,
    `real_reward_per_step`: {per_seed, mean, std_across_seeds, ci95_across_seeds}).
`baselines` holds the two data policies' rows (a CI over the held-out games; there is no seed to
vary), `budget` the budget and seeds, `load_avg_start` / `load_avg_end` the 1-minute load.

Prints a table and ends with one JSON line (`--out FILE` also writes the result to FILE).
Budgets: `--full` is the budget whose output is committed as benchmarks/results/controller.json;
the default is a quick check on the small preset; `--quick` is a smoke test (tiny preset, a few
updates and games; says only that the script runs).

    .venv/bin/python benchmarks/controller.py --full --out benchmarks/results/controller.json
    .venv/bin/python benchmarks/controller.py --quick --seeds 0 1
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.stats

from cdrl.runs.config import RunConfig
from cdrl.runs.train import train_run

RUNS = [
    ("final_proposal", "controller"),
    ("final_proposal", "all"),
    ("reward_prediction", "controller"),
    ("action_loop", "controller"),
]


def reward_summary(run_dir: Path) -> dict:
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    tail = records[-max(1, len(records) // 4):]
    returns = [r["mean_return"] for r in records if r["mean_return"] is not None]
    return {
        "real_reward_per_step": float(np.mean([r["reward"] for r in tail])),
        "predicted_reward_per_step": float(np.mean([r["terms"].get("pred_reward", 0.0) for r in tail])),
        "final_obs_bce": float(np.mean([r["terms"]["obs_bce"] for r in tail])),
        "training_returns_first_last": [returns[0], returns[-1]] if returns else None,
    }


def across_seeds(values: list[float]) -> dict:
    """Mean, standard deviation (ddof 1) and 95 % CI (Student t, n - 1 degrees of freedom) of
    per-seed values; the spread and CI are null for a single seed."""
    n = len(values)
    mean = float(np.mean(values))
    if n < 2:
        return {"per_seed": list(values), "mean": mean, "std_across_seeds": None, "ci95_across_seeds": None}
    std = float(np.std(values, ddof=1))
    half = float(scipy.stats.t.ppf(0.975, n - 1) * std / np.sqrt(n))
    return {"per_seed": list(values), "mean": mean, "std_across_seeds": std,
            "ci95_across_seeds": [mean - half, mean + half]}


BUDGETS = {
    "full": dict(preset="small", steps=150, batch=8, unroll=16, eval_episodes=24, episode_steps=200),
    "default": dict(preset="small", steps=20, batch=4, unroll=8, eval_episodes=8, episode_steps=60),
    "quick": dict(preset="tiny", steps=4, batch=2, unroll=4, eval_episodes=3, episode_steps=20),
}


def _fmt_ci(ci) -> str:
    return f"[{'-':>8s}, {'-':>8s}]" if ci is None else f"[{ci[0]:8.3f}, {ci[1]:8.3f}]"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--full", action="store_true", help="the committed budget (default: a quick check)")
    size.add_argument("--quick", action="store_true",
                      help="a smoke test: tiny preset, 4 updates of 2 games x 4 steps, 3 held-out games of 20 steps")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2],
                        help="seeds trained per configuration (default: 0 1 2)")
    parser.add_argument("--out", default=None, help="also write the JSON result to this file")
    parser.add_argument("--work-dir", default=None, help="where the runs go (default: a temporary directory)")
    args = parser.parse_args(argv)
    seeds = list(dict.fromkeys(args.seeds))
    # Every seed of a configuration runs the same programs (the seed is a traced key): a persistent
    # compilation cache compiles each once (nothing here is timed). JAX_COMPILATION_CACHE_DIR wins.
    import jax

    jax.config.update("jax_compilation_cache_dir", os.environ.get("JAX_COMPILATION_CACHE_DIR")
                      or tempfile.mkdtemp(prefix="cdrl-controller-xla-"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    load_avg_start = os.getloadavg()[0]

    budget_name = "full" if args.full else "quick" if args.quick else "default"
    budget = dict(BUDGETS[budget_name])
    arch_preset = budget.pop("preset")
    warmup = max(1, budget["steps"] // 4)
    work = Path(args.work_dir or tempfile.mkdtemp(prefix="cdrl-controller-"))
    results = {"budget": {**budget, "name": budget_name, "preset": arch_preset, "lr": 0.1, "ascent": 0.1,
                          "warmup_steps": warmup, "noise_std": 0.3, "noise_decay": 0.995, "seeds": seeds},
               "seeds_order": seeds, "load_avg_start": load_avg_start, "runs": {}}
    baselines, baselines_differ = None, False
    for variant, scope in RUNS:
        name = f"{variant}-{scope}" if variant != "action_loop" else variant
        per_seed = {}
        for seed in seeds:
            run_dir = work / name / f"seed{seed}"
            if run_dir.exists():
                shutil.rmtree(run_dir)
            run_dir.parent.mkdir(parents=True, exist_ok=True)
            cfg = RunConfig(variant=variant, preset=arch_preset, scope=scope, ascent=0.1, warmup_steps=warmup,
                            noise_std=0.3, noise_decay=0.995, lr=0.1, seed=seed, eval_every=0,
                            checkpoint_every=budget["steps"], **budget)
            t0 = time.perf_counter()
            summary = train_run(cfg, run_dir)
            wall_s = time.perf_counter() - t0
            policies = summary["policies"]
            per_seed[str(seed)] = {"controller": policies["controller"], **reward_summary(run_dir), "wall_s": wall_s}
            rows = {k: policies[k] for k in ("uniform", "behaviour")}
            if baselines is None:
                baselines = rows
            elif rows != baselines:
                baselines_differ = True
            print(f"{name} seed {seed}: {json.dumps(per_seed[str(seed)])}", file=sys.stderr, flush=True)
        returns = [per_seed[str(s)]["controller"]["mean_return"] for s in seeds]
        ret = across_seeds(returns)
        results["runs"][name] = {
            "variant": variant, "scope": scope, "seeds": per_seed,
            "per_seed_mean_return": returns, "mean_return": ret["mean"],
            "std_across_seeds": ret["std_across_seeds"], "ci95_across_seeds": ret["ci95_across_seeds"],
            "predicted_reward_per_step": across_seeds([per_seed[str(s)]["predicted_reward_per_step"] for s in seeds]),
            "real_reward_per_step": across_seeds([per_seed[str(s)]["real_reward_per_step"] for s in seeds]),
        }
    results["baselines"] = baselines
    if baselines_differ:  # they should not: same games, same fixed policies
        results["warning"] = "the baseline policies' returns differed between runs; `baselines` is the first run's"
        print("warning: " + results["warning"], file=sys.stderr)

    n = len(seeds)
    lines = [f"mean return over {budget['eval_episodes']} held-out games per run; across {n} seed(s) "
             f"{seeds}: mean, 95% CI (Student t, {n - 1} dof); per seed: mean [within-run 95% CI over the games]",
             f"{'policy':36s} {'mean':>8s} {'95% CI across seeds':>20s}   per seed"]
    for name, r in results["runs"].items():
        per = "; ".join(f"{s}: {c['controller']['mean_return']:.2f} [{c['controller']['ci95'][0]:.2f}, "
                        f"{c['controller']['ci95'][1]:.2f}]" for s, c in r["seeds"].items())
        lines.append(f"{'controller ' + name:36s} {r['mean_return']:8.3f} {_fmt_ci(r['ci95_across_seeds'])}   {per}")
    for name, c in baselines.items():
        lines.append(f"{name:36s} {c['mean_return']:8.3f} {'(no seed to vary)':>20s}   "
                     f"CI over the games [{c['ci95'][0]:.2f}, {c['ci95'][1]:.2f}]")
    lines.append("predicted / real reward per step, last quarter of training (mean over seeds; per seed):")
    for name, r in results["runs"].items():
        p, q = r["predicted_reward_per_step"], r["real_reward_per_step"]
        lines.append(f"  {name:34s} {p['mean']:8.4f} / {q['mean']:8.4f}   "
                     + "; ".join(f"{a:.4f} / {b:.4f}" for a, b in zip(p["per_seed"], q["per_seed"])))
    results["load_avg_end"] = os.getloadavg()[0]
    lines.append(f"load average: {load_avg_start:.2f} at the start, {results['load_avg_end']:.2f} at the end")
    print("\n".join(lines))
    line = json.dumps(results)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(results, indent=2) + "\n")
    print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
