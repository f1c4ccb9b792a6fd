"""How well would the planner control with a perfect model and a perfect value?

`cdrl.learners.mpc_planner.oracle_planner` plays the validation games (64 games from seed
10000, 200 steps each) on the level. Each step it scores the eight button combinations held H
steps in the true game, plus γ^H times the value of a policy there (the mean of `--samples`
plays of `--steps` steps), and presses the best. The scripted references play the same games.
The planner itself (`mpc_planner`) replaces only the model and the value with learnt ones.

With `--model-rewards RUN ...`, per run (a controller variant trained with the look-ahead heads
on the level) a half-learnt planner plays instead: `mpc_planner`'s plans (`plan_rollouts`),
scored by the run's reward head, with the played-out value in place of the model's value. It
says what the learnt imagination is worth for control when the value is perfect. The policy
name `model` there takes the run's own value head instead: the planner learnt whole, offline.

With `--delay` the oracle planners act a step late (`delayed`), as `mpc_planner` did before it
planned from the real frame.

    .venv/bin/python experiments/controller/oracle_planner_study.py [--level turned]
        [--policies never_accelerate uniform privileged] [--horizons 5] [--gamma 0.9]
        [--delay] [--model-rewards RUN ...] [--out FILE]

Ends with one JSON line.
"""
from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

if not __package__:  # run as a file, not with -m: the repository root on the path (benchmarks/, experiments/)
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import emit  # noqa: E402


def model_reward_planner(run_dir: Path, policy, gamma: float, horizon: int, samples: int, steps: int):
    """(game, game parameters, a privileged policy): the run's planner (`mpc_planner`'s plans,
    scored by its reward head), with the value at the plans' ends `policy`'s, played out in the
    true game from the state after the plan's buttons; for `policy` None, the run's own
    planner (`plan_scores`: its value heads)."""
    import jax
    import jax.numpy as jnp

    from cdrl.analysis.imagination_video import load_run
    from cdrl.data.frames import model_obs
    from cdrl.evaluation.probe_ceiling import policy_value
    from cdrl.learners.mpc_planner import game_plans, plan_rollouts, plan_scores
    from cdrl.models.base import BUTTON_COMBOS
    from cdrl.models.base import StepInput
    from cdrl.training import lookahead
    from envs.policies import Policy

    cfg, variant, params, _, game, env_params = load_run(run_dir, "lookahead")
    look, heads = cfg.lookahead_hparams(), params["lookahead"]
    combos = jnp.asarray(BUTTON_COMBOS)
    discounts = gamma ** jnp.arange(horizon, dtype=jnp.float32)

    def init(key):
        del key
        return {"carry": variant.init_carry(1), "is_first": jnp.ones((1,), bool)}

    def step(key, ps, obs, state, env_params):
        x = StepInput(obs=model_obs(obs, variant.arch)[None], action=jnp.zeros((1, 3)), is_first=ps["is_first"])
        if policy is None:  # the run's planner whole: `mpc_planner`'s scores
            scores = plan_scores(variant, look, params, ps["carry"], x, gamma, horizon)[0]
        else:
            h = plan_rollouts(variant, params, ps["carry"], x, horizon)[1]
            rewards = lookahead.reward(heads, h, look)[..., 0] @ discounts
            k_plan, k_value = jax.random.split(key)
            ends, on, _ = game_plans(game, env_params, state, horizon, k_plan)
            value = policy_value(game, env_params, policy, gamma, k_value, ends, on, samples=samples, steps=steps)
            scores = rewards + gamma ** horizon * value
        best = combos[jnp.argmax(scores)]
        carry = variant.step(params, ps["carry"], x.replace(action=best[None]))[0]
        return best, {"carry": carry, "is_first": jnp.zeros((1,), bool)}

    return game, env_params, Policy(f"model_reward_planner({run_dir.name})", init, step, privileged=True)


def delayed(game, planner):
    """`planner` acting a step late, as `mpc_planner` did: it plans from the game's state after
    the pending buttons (the game's randomness of that step drawn anew) and presses its choice
    next step."""
    import jax
    import jax.numpy as jnp

    from envs.policies import Policy

    def init(key):
        return {"inner": planner.init(key), "action": jnp.zeros((3,))}

    def step(key, ps, obs, state, env_params):
        k_now, k_plan = jax.random.split(key)
        now = game.step_state(k_now, state, ps["action"], env_params)[0]
        best, inner = planner.step(k_plan, ps["inner"], obs, now, env_params)
        return ps["action"], {"inner": inner, "action": best}

    return Policy(f"delayed({planner.name})", init, step, privileged=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--level", default="turned")
    parser.add_argument("--policies", nargs="+", default=["never_accelerate", "uniform", "privileged"],
                        help="the policies whose value ends the plans (with --model-rewards, `model`: the "
                        "run's value head)")
    parser.add_argument("--horizons", type=int, nargs="+", default=[5])
    parser.add_argument("--gamma", type=float, default=0.9)
    parser.add_argument("--samples", type=int, default=4, help="plays averaged into each value")
    parser.add_argument("--steps", type=int, default=30, help="steps of each play")
    parser.add_argument("--games", type=int, default=64)
    parser.add_argument("--episode-steps", type=int, default=200)
    parser.add_argument("--delay", action="store_true", help="the oracle planners act a step late (`delayed`)")
    parser.add_argument("--model-rewards", nargs="*", default=[], help="runs whose imagined rewards plan (see above)")
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
    for horizon in [] if args.model_rewards else args.horizons:
        for name in args.policies:
            start = time.perf_counter()
            oracle = oracle_planner(game, continuation_policy(game, name), args.gamma, horizon, samples=args.samples,
                                    steps=args.steps)
            oracle = delayed(game, oracle) if args.delay else oracle
            row = play.summarize(*play.play(game, env_params, oracle.init, oracle.step, seeds, args.episode_steps,
                                            privileged=True))
            row.update(value_policy=name, horizon=horizon, delay=int(args.delay),
                       seconds=round(time.perf_counter() - start, 1))
            result["planners"].append(row)
            print(f"H {horizon}, value of {name}: {row['mean_return']:+.2f} [{row['ci95'][0]:.2f}, "
                  f"{row['ci95'][1]:.2f}] ({row['seconds']} s)", file=sys.stderr, flush=True)
    for run, horizon, name in itertools.product(args.model_rewards, args.horizons, args.policies):
        start = time.perf_counter()
        value_of = None if name == "model" else continuation_policy(game, name)
        g, p, planner = model_reward_planner(Path(run), value_of, args.gamma, horizon, args.samples, args.steps)
        if p.max_steps != env_params.max_steps:
            raise SystemExit(f"run {run} plays {int(p.max_steps)} steps a game, not {args.episode_steps}")
        row = play.summarize(*play.play(g, p, planner.init, planner.step, seeds, args.episode_steps, privileged=True))
        row.update(run=run, rewards="model", value_policy=name, horizon=horizon,
                   seconds=round(time.perf_counter() - start, 1))
        result["planners"].append(row)
        print(f"{run}: the model's rewards, H {horizon}, value of {name}: {row['mean_return']:+.2f} "
              f"[{row['ci95'][0]:.2f}, {row['ci95'][1]:.2f}] ({row['seconds']} s)", file=sys.stderr, flush=True)
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
