"""Does a run's learnt planner rank the eight buttons of one state as the true game does?

The planner scores each button combination b of a state s by r̂(s, b) + γ V̂(s, b): the reward
head after the real frame, then the value after that reward (with `--horizon` H, b held H
steps: their discounted rewards, then γ^H times the value). The true game gives each the
rewards and the played-out value V(s_b) of a continuation policy (`--policy`, the mean of
`--samples` plays of `--steps` steps; `probe_ceiling.policy_value`). The states are
those of the continuation policy's own play of `--games` held-out games.

Per state the probe compares the eight learnt scores with the eight true ones: their Pearson
correlation, whether their best buttons agree, and the spread (best minus worst) of each. It
does the same for the reward part and the value part alone, and for the four combinations that
do not accelerate (the steering). Over the states it gives the correlation of the scores'
means: how well the levels are learnt.

    .venv/bin/python experiments/controller/branch_value_probe.py RUN [RUN ...] --out F
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

if not __package__:  # run as a file, not with -m: the repository root on the path (benchmarks/, experiments/)
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import emit  # noqa: E402


def branch_trace(run_dir: Path, policy_name: str, gamma: float, games: int, length: int, steps: int, samples: int,
                 horizon: int = 1):
    """Per game, step and button combination `[games, length, 8]`: the learnt reward and the
    discounted learnt value after it, the true ones; and per game and step `[games, length]`
    whether the game was on. `horizon`: the combination held that many steps."""
    import jax
    import jax.numpy as jnp

    from cdrl.analysis.imagination_video import load_run
    from cdrl.data.frames import model_obs
    from cdrl.evaluation import play
    from cdrl.evaluation.probe_ceiling import continuation_policy, policy_value
    from cdrl.learners.imagination import lookahead_heads
    from cdrl.learners.mpc_planner import game_plans, plan_rollouts
    from cdrl.models.base import StepInput
    from cdrl.training import lookahead

    cfg, variant, params, _, game, env_params = load_run(run_dir, "lookahead")
    look = cfg.lookahead_hparams()
    heads = lookahead_heads(look, params)
    policy = continuation_policy(game, policy_name)

    def act(key, ps, state):
        return policy.step(key, ps, None, state, env_params) if policy.privileged else policy.step(key, ps, None)

    def one_game(key):
        k_reset, k_init, k_run = jax.random.split(key, 3)
        obs, state = game.reset(k_reset, env_params)

        def body(c, k):
            state, obs, carry, ps, first, on = c
            k_act, k_env, k_plan, k_value = jax.random.split(k, 4)
            x = StepInput(obs=model_obs(obs, variant.arch)[None], action=jnp.zeros((1, 3)), is_first=first)
            _, h, last = plan_rollouts(variant, params, carry, x, horizon, last_frame=look.frame_value)
            r_hat = lookahead.reward(heads, h, look)[:, :, 0] @ (gamma ** jnp.arange(horizon))  # [8]
            if look.advantage:  # the planner ranks by the advantage alone
                r_hat, v_hat = jnp.zeros_like(r_hat), lookahead.advantage(heads, h[:, 0, 0]) / gamma ** horizon
            elif look.frame_value:
                v_hat = lookahead.frame_value(heads, last, variant.arch, look)[:, 0]
            else:
                v_hat = lookahead.value_after(heads, h[:, -1, 0], look)
            ends, alive, r_true = game_plans(game, env_params, state, horizon, k_plan)
            v_true = policy_value(game, env_params, policy, gamma, k_value, ends, alive, samples=samples,
                                  steps=steps)
            r_true = (gamma ** jnp.arange(horizon)) @ r_true
            a, ps = act(k_act, ps, state)
            carry = variant.step(params, carry, x.replace(action=a[None]))[0]
            obs, state, _, term, trunc, _ = game.step(k_env, state, a, env_params)
            out = (r_hat, gamma ** horizon * v_hat, r_true, gamma ** horizon * v_true, on)
            return (state, obs, carry, ps, jnp.zeros((1,), bool), on & ~(term | trunc)), out

        c0 = (state, obs, variant.init_carry(1), policy.init(k_init), jnp.ones((1,), bool), jnp.array(True))
        return jax.lax.scan(body, c0, jax.random.split(k_run, length))[1]

    keys = jax.vmap(jax.random.PRNGKey)(play.EVAL_SEED + jnp.arange(games))
    return [jax.device_get(x) for x in jax.jit(jax.vmap(one_game))(keys)]


def scores(trace) -> dict:
    """The probe's numbers (see the module docstring) from `branch_trace`'s arrays."""
    import numpy as np

    from cdrl.models.base import BUTTON_COMBOS

    r_hat, v_hat, r_true, v_true, on = (np.asarray(x, np.float64) for x in trace)
    on = on.astype(bool)
    pick = lambda x: x[on]  # noqa: E731  [states, 8]

    def compare(learnt, true):
        learnt, true = pick(learnt), pick(true)
        ok = (learnt.std(-1) > 0) & (true.std(-1) > 0)
        lc, tc = learnt - learnt.mean(-1, keepdims=True), true - true.mean(-1, keepdims=True)
        corr = (lc * tc).sum(-1) / np.sqrt((lc ** 2).sum(-1) * (tc ** 2).sum(-1) + 1e-300)
        best = true[np.arange(len(true)), learnt.argmax(-1)] >= true.max(-1) - 1e-9
        means = np.corrcoef(learnt.mean(-1), true.mean(-1))[0, 1] if learnt.mean(-1).std() > 0 else None
        return {"corr_within": float(corr[ok].mean()) if ok.any() else None, "best_agrees": float(best.mean()),
                "spread_learnt": float(np.median(np.ptp(learnt, -1))), "spread_true": float(np.median(np.ptp(true, -1))),
                "level_std_true": float(true.mean(-1).std()), "corr_levels": None if means is None else float(means)}

    steer = BUTTON_COMBOS[:, 2] == 0  # the four combinations that do not accelerate: the steering
    return {"states": int(on.sum()), "score": compare(r_hat + v_hat, r_true + v_true),
            "reward": compare(r_hat, r_true), "value": compare(v_hat, v_true),
            "steer_score": compare((r_hat + v_hat)[..., steer], (r_true + v_true)[..., steer]),
            "steer_value": compare(v_hat[..., steer], v_true[..., steer])}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="runs with the look-ahead heads")
    parser.add_argument("--policy", default="never_accelerate", help="the continuation policy: the play and its value")
    parser.add_argument("--gamma", type=float, default=0.9)
    parser.add_argument("--games", type=int, default=16)
    parser.add_argument("--length", type=int, default=100, help="steps of each game probed")
    parser.add_argument("--samples", type=int, default=4, help="plays averaged into each true value")
    parser.add_argument("--steps", type=int, default=30, help="steps of each play")
    parser.add_argument("--horizon", type=int, default=1, help="steps each combination is held (the planner's H)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    from cdrl.evaluation import play

    result = {"experiment": "branch_value_probe", "policy": args.policy, "gamma": args.gamma, "games": args.games,
              "first_seed": play.EVAL_SEED, "length": args.length, "samples": args.samples, "steps": args.steps,
              "horizon": args.horizon,
              "runs": {}}
    for run in args.runs:
        row = scores(branch_trace(Path(run), args.policy, args.gamma, args.games, args.length, args.steps,
                                  args.samples, args.horizon))
        result["runs"][run] = row
        for part in ("score", "value", "steer_score", "steer_value"):
            s = row[part]
            print(f"{run} {part}: within-state corr {s['corr_within']:+.2f}, best agrees {s['best_agrees']:.2f}, "
                  f"spread learnt {s['spread_learnt']:.3f} true {s['spread_true']:.3f}, levels corr "
                  f"{s['corr_levels']:+.2f}", file=sys.stderr, flush=True)
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
