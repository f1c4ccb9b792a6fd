"""How well would the planner control with a perfect model and a perfect value?

`cdrl.learners.mpc_planner.oracle_planner` plays the validation games (64 games from seed
10000, 200 steps each) on the level. Each step it scores the eight button combinations held H
steps in the true game, plus γ^H times the value of a policy there (the mean of `--samples`
plays of `--steps` steps), and presses the best. The scripted references play the same games.
The planner itself (`mpc_planner`) replaces only the model and the value with learnt ones.

With `--model-rewards RUN ...`, per run (a controller variant trained with the look-ahead heads
on the level) a half-learnt planner plays too: `mpc_planner`'s own step (the model fed the frame
and the pending buttons, a step of delay, the plans imagined by the model and scored by its
reward head), with the played-out value in place of the model's value. It says what the learnt
imagination is worth for control when the value is perfect.

    .venv/bin/python experiments/controller/oracle_planner_study.py [--level turned]
        [--policies never_accelerate uniform privileged] [--horizons 5] [--gamma 0.9]
        [--model-rewards RUN ...] [--out FILE]

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


def model_reward_planner(run_dir: Path, policy, gamma: float, horizon: int, samples: int, steps: int):
    """(game, game parameters, a privileged policy): the run's planner, its plans' rewards from
    its imagination, the value at their ends `policy`'s played out in the true game from the
    state after the pending buttons and the plan's."""
    import jax
    import jax.numpy as jnp

    from cdrl.analysis.imagination_video import load_run
    from cdrl.data.frames import model_obs
    from cdrl.evaluation.probe_ceiling import policy_value
    from cdrl.learners.replay_base import BUTTON_COMBOS
    from cdrl.models.base import StepInput
    from cdrl.training import lookahead
    from envs.policies import Policy

    cfg, variant, params, _, game, env_params = load_run(run_dir, "lookahead")
    look, heads = cfg.lookahead_hparams(), params["lookahead"]
    combos = jnp.asarray(BUTTON_COMBOS)
    discounts = gamma ** jnp.arange(horizon, dtype=jnp.float32)

    def init(key):
        del key
        return {"carry": variant.init_carry(1), "action": jnp.zeros((1, 3)), "is_first": jnp.ones((1,), bool)}

    def imagined(carry, frame, buttons):
        def body(c, _):
            carry, frame = c
            carry, out = variant.imagine_step(params, carry, frame, buttons[None])
            frame = jax.nn.sigmoid(out["logits"]) if "logits" in out else frame
            return (carry, frame), variant.features(carry)

        h = jax.lax.scan(body, (carry, frame), None, length=horizon)[1]
        return discounts @ lookahead.reward(heads, h, look)[:, 0]

    def held(c, k):
        s, on = c
        s, reward, term, trunc, _ = jax.vmap(game.step_state, (None, 0, 0, None))(k, s, combos, env_params)
        return (s, on & ~(term | trunc)), None

    def step(key, ps, obs, state, env_params):
        x = StepInput(obs=model_obs(obs, variant.arch)[None], action=ps["action"], is_first=ps["is_first"])
        carry, out = variant.step(params, ps["carry"], x)
        rewards = jax.vmap(imagined, (None, None, 0))(carry, jax.nn.sigmoid(out["logits"]), combos)
        k_now, k_plan, k_value = jax.random.split(key, 3)
        now = game.step_state(k_now, state, ps["action"][0], env_params)[0]
        states = jax.tree.map(lambda x: jnp.broadcast_to(x, combos.shape[:1] + x.shape), now)
        ends, on = jax.lax.scan(held, (states, jnp.ones(combos.shape[0], bool)), jax.random.split(k_plan, horizon))[0]
        value = policy_value(game, env_params, policy, gamma, k_value, ends, on, samples=samples, steps=steps)
        best = combos[jnp.argmax(rewards + gamma ** horizon * value)]
        return ps["action"][0], {"carry": carry, "action": best[None], "is_first": jnp.zeros((1,), bool)}

    return game, env_params, Policy(f"model_reward_planner({run_dir.name})", init, step, privileged=True)


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
            row = play.summarize(*play.play(game, env_params, oracle.init, oracle.step, seeds, args.episode_steps,
                                            privileged=True))
            row.update(value_policy=name, horizon=horizon, seconds=round(time.perf_counter() - start, 1))
            result["planners"].append(row)
            print(f"H {horizon}, value of {name}: {row['mean_return']:+.2f} [{row['ci95'][0]:.2f}, "
                  f"{row['ci95'][1]:.2f}] ({row['seconds']} s)", file=sys.stderr, flush=True)
    for run in args.model_rewards:
        for name in args.policies:
            start = time.perf_counter()
            g, p, planner = model_reward_planner(Path(run), continuation_policy(game, name), args.gamma,
                                                 args.horizons[0], args.samples, args.steps)
            if p.max_steps != env_params.max_steps:
                raise SystemExit(f"run {run} plays {int(p.max_steps)} steps a game, not {args.episode_steps}")
            row = play.summarize(*play.play(g, p, planner.init, planner.step, seeds, args.episode_steps,
                                            privileged=True))
            row.update(run=run, rewards="model", value_policy=name, horizon=args.horizons[0],
                       seconds=round(time.perf_counter() - start, 1))
            result["planners"].append(row)
            print(f"{run}: the model's rewards, H {args.horizons[0]}, value of {name}: {row['mean_return']:+.2f} "
                  f"[{row['ci95'][0]:.2f}, {row['ci95'][1]:.2f}] ({row['seconds']} s)", file=sys.stderr, flush=True)
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
