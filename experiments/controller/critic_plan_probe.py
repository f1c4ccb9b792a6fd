"""Does one step of look-ahead through the world model improve a trained controller?

A run of a replay learner (`onpolicy_ac`, for example) has a controller and a world model that
predicts reward. The controller draws the buttons a_t from h_{t-1}, before it sees o_t. Here the
model also sees o_t: each of the eight button combinations gets its predicted reward r̂(o_t, a)
(`mpc_planner.plan_rollouts`, one step). The buttons pressed are

    argmax_a  log π(a) + κ (r̂(a) + w γ V(h_t(a))),

π the controller's independent buttons, V the learner's critic (fitted to the returns after
a_t's reward) on the model's state after a. κ 0 is the controller alone (its buttons taken at
0.5, fed back as pressed); a large κ is the one-step plan alone. It is `onpolicy_ac`'s critic
plan (`critic_plan_fns`) with γ scaled by `--critic-weight w` (w 0: the reward head alone).

    .venv/bin/python experiments/controller/critic_plan_probe.py RUN [RUN ...] [--kappas 0 30 100 300 1000 1e5]
        [--critic-weight 1] [--games 64] [--out FILE]

Validation games (seeds 10000 and up) only: this probe makes a choice. Ends with one JSON line.
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
    parser.add_argument("runs", nargs="+", help="run directories of a replay learner with a reward head")
    parser.add_argument("--kappas", type=float, nargs="+", default=[0.0, 30.0, 100.0, 300.0, 1000.0, 1e5])
    parser.add_argument("--critic-weight", type=float, default=1.0, help="w: the critic's weight in Q (default 1)")
    parser.add_argument("--games", type=int, default=64)
    parser.add_argument("--episode-steps", type=int, default=200)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    import jax.numpy as jnp
    import numpy as np

    from cdrl.evaluation import play
    from cdrl.learners.onpolicy_ac import critic_plan_fns
    from cdrl.runs.online import restore_learner
    from cdrl.runs.rundir import RunDir

    seeds = np.arange(play.EVAL_SEED, play.EVAL_SEED + args.games)
    result = {"experiment": "critic_plan_probe", "games": args.games, "first_seed": play.EVAL_SEED,
              "episode_steps": args.episode_steps, "runs": {}}
    for run in args.runs:
        cfg, learner, state = restore_learner(RunDir(Path(run)))
        variant, params, game = learner.model, learner.world_model(state), learner.game
        env_params = learner.env_params.replace(max_steps=np.asarray(args.episode_steps, np.int32))
        init, act = critic_plan_fns(variant)
        fixed = {"model": params, "critic": state.critic, "gamma": jnp.float32(args.critic_weight * cfg.gamma)}
        rows = {"controller": play.summarize(*play.play(game, env_params, *play.controller_fns(variant), seeds,
                                                        args.episode_steps, params=params))}
        for kappa in args.kappas:
            start = time.perf_counter()
            row = play.summarize(*play.play(game, env_params, init, act, seeds, args.episode_steps,
                                            params={**fixed, "kappa": jnp.float32(kappa)}))
            rows[f"kappa {kappa:g}"] = {**row, "seconds": round(time.perf_counter() - start, 1)}
        result["runs"][run] = {"learner": cfg.learner, "variant": cfg.variant, "level": cfg.level,
                               "step": int(state.model.step), "critic_weight": args.critic_weight, "rows": rows}
        for name, row in rows.items():
            print(f"{run} {name}: {row['mean_return']:+.2f} [{row['ci95'][0]:.2f}, {row['ci95'][1]:.2f}] "
                  f"length {row['mean_length']:.1f}", file=sys.stderr, flush=True)
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
