"""How well could a perfect model and a perfect value rank the steering in the imagination probe?

For each continuation policy and discount: `cdrl.evaluation.probe_ceiling.ceiling` on the probe's
own starts (32 games from seed 20000, a start every 10 steps of 200). A sequence is scored by
its real first H rewards, then also plus γ^H times the policy's value after them (the mean of
`--samples` played continuations of `--steps` steps). The answer bounds every world model whose
value is fitted to that policy's returns.

With `--runs`, per run (a controller variant trained with a value head on the level): which half
of its look-ahead loses the ranking (`probe_ceiling.attribution`). Its imagined rewards or its
value are swapped for the game's, the value played out by the policy of the run's data at the
run's γ.

    .venv/bin/python experiments/world_models/ceiling_study.py [--level turned]
        [--policies uniform privileged] [--gammas 0.9] [--samples 8] [--steps 50] [--runs DIR ...]
        [--out FILE]

Ends with one JSON line.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

if not __package__:  # run as a file, not with -m: the repository root on the path (benchmarks/, experiments/)
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import emit  # noqa: E402

import numpy as np  # noqa: E402


def attribute(run_dir: Path, args) -> dict:
    """The run's `attribution` on the probe's starts, and the figures of each half."""
    from cdrl.analysis.imagination_video import load_run
    from cdrl.evaluation import imagination_probe as ip
    from cdrl.evaluation import probe_ceiling as pc
    from cdrl.runs.sources import data_policy

    cfg, variant, params, step, game, env_params = load_run(run_dir)
    hp = cfg.lookahead_hparams()
    if hp is None:
        raise SystemExit(f"run {run_dir} has no value head to attribute (train it with --lookahead-steps)")
    points = args.episode_steps // 10 - 1
    model = ip.followed_branches(variant, params, game, env_params, hp, games=args.games, points=points, every=10,
                                 horizon=ip.HORIZON)
    policy = data_policy(cfg)
    played = pc.branches(game, env_params, pc.continuation_policy(game, policy), cfg.gamma, games=args.games,
                         points=points, every=10, samples=args.samples, steps=args.steps)
    if not (np.array_equal(model["alive"], played["alive"]) and np.array_equal(model["real"], played["real"])):
        raise SystemExit(f"run {run_dir}: the probe's starts differ from the ceiling's (level or step limit)")
    alive = model["alive"]
    figures = pc.attribution(model["imagined"][alive], model["value"][alive], model["real"][alive],
                             played["value"][alive], cfg.gamma)
    for name, rows in figures.items():
        print(f"{run_dir.name} {name:>12}: agree H 1/3/5 "
              + " / ".join(f"{rows[h]['best_steer_agree']:.2f}" for h in rows) + "; corr_steer "
              + " / ".join(f"{rows[h]['corr_steer'] or 0:.2f}" for h in rows), file=sys.stderr, flush=True)
    return {"run": str(run_dir), "step": step, "variant": cfg.variant, "gamma": cfg.gamma, "value_policy": policy,
            "starts": int(alive.sum()), **figures}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--level", default="turned")
    parser.add_argument("--policies", nargs="+", default=["uniform", "held_uniform", "behaviour", "never_accelerate",
                                                          "privileged"])
    parser.add_argument("--gammas", type=float, nargs="+", default=[0.9])
    parser.add_argument("--samples", type=int, default=8, help="continuations averaged into each value")
    parser.add_argument("--steps", type=int, default=50, help="steps of each continuation")
    parser.add_argument("--games", type=int, default=32)
    parser.add_argument("--episode-steps", type=int, default=200, help="the games' step limit (the runs')")
    parser.add_argument("--runs", nargs="*", default=[], help="runs whose look-ahead to attribute (then no --policies)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    from cdrl.evaluation import imagination_probe as ip
    from cdrl.evaluation.probe_ceiling import ceiling
    from envs.slither import level_game, level_params

    game = level_game(args.level)
    env_params = level_params(args.level).replace(max_steps=np.asarray(args.episode_steps, np.int32))
    result = {"experiment": "ceiling_study", "level": args.level, "games": args.games, "every": 10,
              "horizon": ip.HORIZON, "explore": ip.EXPLORE, "episode_steps": args.episode_steps,
              "samples": args.samples, "steps": args.steps, "rows": []}
    if args.runs:
        result["runs"] = [attribute(Path(run), args) for run in args.runs]
        emit(result, args.out)
        return 0
    for gamma in args.gammas:
        for policy in args.policies:
            start = time.perf_counter()
            row = ceiling(game, env_params, policy, gamma, max_steps=args.episode_steps, games=args.games,
                          samples=args.samples, steps=args.steps)
            row["seconds"] = round(time.perf_counter() - start, 1)
            result["rows"].append(row)
            agree = " / ".join(f"{row['with_value'][h]['best_steer_agree']:.2f}" for h in row["with_value"])
            alone = " / ".join(f"{row['rewards_only'][h]['best_steer_agree']:.2f}" for h in row["rewards_only"])
            print(f"{policy:>16} γ {gamma}: agree with value H {'/'.join(row['with_value'])} {agree}; "
                  f"rewards only {alone}; straight {row['with_value']['1']['always_straight_agree']:.2f} "
                  f"({row['seconds']} s)", file=sys.stderr, flush=True)
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
