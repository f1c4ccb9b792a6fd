"""How well would the planner control with a perfect model and a perfect value?

`cdrl.learners.mpc_planner.oracle_planner` plays the validation games (64 games from seed
10000, 200 steps each) on the level. Each step it scores the eight button combinations held H
steps in the true game, plus γ^H times the value of a policy there (the mean of `--samples`
plays of `--steps` steps), and presses the best. The scripted references play the same games.
The planner itself (`mpc_planner`) replaces only the model and the value with learnt ones.

    .venv/bin/python experiments/controller/oracle_planner_study.py [--level turned]
        [--policies never_accelerate uniform privileged] [--horizons 5] [--gamma 0.9] [--out FILE]

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


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--level", default="turned")
    parser.add_argument("--policies", nargs="+", default=["never_accelerate", "uniform", "privileged"],
                        help="the policies whose value ends the plans")
    parser.add_argument("--horizons", type=int, nargs="+", default=[5])
    parser.add_argument("--gamma", type=float, default=0.9)
    parser.add_argument("--samples", type=int, default=4, help="plays averaged into each value")
    parser.add_argument("--steps", type=int, default=30, help="steps of each play")
    parser.add_argument("--games", type=int, default=64)
    parser.add_argument("--episode-steps", type=int, default=200)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    import numpy as np

    from cdrl.evaluation import play
    from cdrl.evaluation.probe_ceiling import continuation_policy
    from cdrl.learners.mpc_planner import oracle_planner
    from envs.slither import level_game, level_params

    game = level_game(args.level)
    env_params = level_params(args.level).replace(max_steps=np.asarray(args.episode_steps, np.int32))
    seeds = np.arange(play.EVAL_SEED, play.EVAL_SEED + args.games)
    result = {"experiment": "oracle_planner_study", "level": args.level, "games": args.games,
              "first_seed": play.EVAL_SEED, "episode_steps": args.episode_steps, "gamma": args.gamma,
              "samples": args.samples, "steps": args.steps, "references": {}, "planners": []}
    for name in play.REFERENCES:
        ref = play.reference_policy(game, name)
        result["references"][name] = play.summarize(*play.play(game, env_params, ref.init, ref.step, seeds,
                                                                args.episode_steps, privileged=ref.privileged))
    for horizon in args.horizons:
        for name in args.policies:
            start = time.perf_counter()
            oracle = oracle_planner(game, continuation_policy(game, name), args.gamma, horizon, samples=args.samples,
                                    steps=args.steps)
            row = play.summarize(*play.play(game, env_params, oracle.init, oracle.step, seeds, args.episode_steps,
                                            privileged=True))
            row.update(value_policy=name, horizon=horizon, seconds=round(time.perf_counter() - start, 1))
            result["planners"].append(row)
            print(f"H {horizon}, value of {name}: {row['mean_return']:+.2f} [{row['ci95'][0]:.2f}, "
                  f"{row['ci95'][1]:.2f}] ({row['seconds']} s)", file=sys.stderr, flush=True)
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
