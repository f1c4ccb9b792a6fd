"""The controller experiment: train controller variants online against the built-in game and
compare their noise-free play with the thesis's two data policies on the same held-out seeds.

Runs (each `cdrl train` with the same budget and seed):
  final_proposal, scope controller  (reward ascent moves only the controller D_a)
  final_proposal, scope all         (the thesis's literal wording)
  reward_prediction, scope controller (open loop on observations: does closed loop − help?)
  action_loop                        (no reward head: no ascent; BCE only)

Prints a return table and, per run, the mean predicted vs real reward per step over the last
quarter of training (is reward hallucinated?), and ends with one JSON line. `--full` is the
budget whose output is committed as benchmarks/results/controller.json.

    .venv/bin/python benchmarks/controller.py --full --out benchmarks/results/controller.json
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

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


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="the committed budget (default: a quick check)")
    parser.add_argument("--out", default=None, help="also write the JSON result to this file")
    parser.add_argument("--work-dir", default=None, help="where the runs go (default: a temporary directory)")
    args = parser.parse_args(argv)

    budget = dict(steps=150, batch=8, unroll=16, eval_episodes=24, episode_steps=200) if args.full else \
        dict(steps=20, batch=4, unroll=8, eval_episodes=8, episode_steps=60)
    work = Path(args.work_dir or tempfile.mkdtemp(prefix="cdrl-controller-"))
    results = {"budget": {**budget, "preset": "small", "lr": 0.1, "ascent": 0.1, "warmup_steps": budget["steps"] // 4,
                          "noise_std": 0.3, "seed": 0}, "runs": {}}
    table = None
    for variant, scope in RUNS:
        name = f"{variant}-{scope}" if variant != "action_loop" else variant
        run_dir = work / name
        if run_dir.exists():
            shutil.rmtree(run_dir)
        cfg = RunConfig(variant=variant, preset="small", scope=scope, ascent=0.1, warmup_steps=budget["steps"] // 4,
                        noise_std=0.3, noise_decay=0.995, lr=0.1, seed=0, eval_every=0,
                        checkpoint_every=budget["steps"], **budget)
        summary = train_run(cfg, run_dir)
        policies = summary["policies"]
        results["runs"][name] = {"controller": policies["controller"], **reward_summary(run_dir)}
        table = {k: policies[k] for k in ("uniform", "behaviour")}
        print(f"{name}: {json.dumps(results['runs'][name])}", file=sys.stderr)
    results["baselines"] = table
    lines = [f"{'policy':34s} {'mean return':>11s} {'95% CI':>20s} {'pred/real reward per step':>27s}"]
    for name, r in results["runs"].items():
        c = r["controller"]
        lines.append(f"{'controller ' + name:34s} {c['mean_return']:11.3f} [{c['ci95'][0]:8.3f}, {c['ci95'][1]:8.3f}]"
                     f" {r['predicted_reward_per_step']:12.4f} / {r['real_reward_per_step']:.4f}")
    for name, c in table.items():
        lines.append(f"{name:34s} {c['mean_return']:11.3f} [{c['ci95'][0]:8.3f}, {c['ci95'][1]:8.3f}]")
    print("\n".join(lines))
    line = json.dumps(results)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(results, indent=2) + "\n")
    print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
