"""Does imagination tell which way to steer? A world model's imagined returns against the game's.

The privileged policy (a fifth of its steps random turns) plays `--games` games (seeds 20000,
20001, ...: neither training nor held-out games) while the run's world model, teacher-forced on
the frames and the buttons executed, follows it. Every `--every` steps, from that real state,
four fixed button sequences are played for `--horizon` steps twice: by the game itself (from its
state at that step, the same game randomness for every sequence) and by the model's
imagination (`Variant.imagine_step` fed its own predictions, as the `imagine`, `critic` and
`value` controllers imagine). The sequences: straight on, turn button 0 held, turn button 1
held (none accelerating), and straight on accelerating. Reward counted up to an episode's end.

Reported for the returns summed over the first k imagined steps (k in `--ks`):

- `corr_all`: correlation of imagined and real returns over every (start, sequence);
- `corr_steer`: the same over the three non-accelerating sequences after subtracting each
  start's mean over them: whether imagination sees what steering changes, the part of the
  return a controller's choice of direction decides;
- `best_steer_agree`: over the starts where the three steering sequences' real returns have one
  best, the share where imagination ranks that one first (a random ranking: 1/3);
- `best_share_real`, `best_share_imagined`: over those starts, how often each steering sequence
  is the best (in the game; in imagination): a preference for one direction whatever the state.
  The largest real share is what always naming that one sequence would agree (the privileged
  policy steers towards pellets, so straight on is often best), the bar `best_steer_agree` has
  to clear to show that imagination tells the states apart;
- `mean_real`, `mean_imagined`: each sequence's mean return over the starts (an imagination
  that promises more than the game gives is one a controller can exploit);
- `accelerate_gap`: the mean real and imagined return of straight-on accelerating minus
  straight on (the cost of accelerating, which imagination is known to see).

    .venv/bin/python experiments/control_probes/imagination_probe.py RUN_DIR [RUN_DIR ...] [--out FILE]

RUN_DIR: a controller variant's run on the built-in game (offline, `--controller none`, or
online). Ends with one JSON line, a result per run.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

if not __package__:  # run as a file, not with -m: the repository root on the path (benchmarks/, experiments/)
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import emit  # noqa: E402

EXPLORE = 0.2  # the share of the privileged policy's steps replaced by random turns
GAME_SEED = 20000
SEQUENCES = {"straight": (0.0, 0.0, 0.0), "turn0": (1.0, 0.0, 0.0), "turn1": (0.0, 1.0, 0.0),
             "accelerate": (0.0, 0.0, 1.0)}
STEER = 3  # the first three sequences do not accelerate


def branch_returns(variant, params, game, env_params, horizon: int, every: int, games: int, max_steps: int):
    """Per game and branch point: the real and imagined reward of every sequence at every
    imagined step `[games, points, sequences, horizon]`, and whether the game was on there."""
    import jax
    import jax.numpy as jnp

    from experiments.control_probes.followed_play import follow_step, start

    buttons = jnp.asarray(list(SEQUENCES.values()), jnp.float32)
    n = buttons.shape[0]

    def real(key, state):
        def body(c, k):
            state, on = c
            _, state, reward, term, trunc, _ = jax.vmap(game.step, (None, 0, 0, None))(k, state, buttons, env_params)
            return (state, on & ~(term | trunc)), reward * on

        states = jax.tree.map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), state)
        return jax.lax.scan(body, (states, jnp.ones(n, bool)), jax.random.split(key, horizon))[1]

    def imagined(carry, frame):
        def body(c, _):
            carry, frame = c
            carry, out = variant.imagine_step(params, carry, frame, buttons)
            frame = jax.nn.sigmoid(out["logits"]) if "logits" in out else frame
            return (carry, frame), out["reward"]

        carries = jax.tree.map(lambda x: jnp.repeat(x, n, axis=0), carry)
        return jax.lax.scan(body, (carries, jnp.repeat(frame, n, axis=0)), None, length=horizon)[1]

    follow = follow_step(variant, params, game, env_params, EXPLORE)

    def block(c, _):
        c = jax.lax.scan(follow, c, None, length=every)[0]
        state, _, carry, _, key, alive, pred = c
        return c, (real(jax.random.fold_in(key, 1), state), imagined(carry, pred), alive)

    def one(key):
        return jax.lax.scan(block, start(variant, game, env_params, key), None, length=max_steps // every - 1)[1]

    keys = jax.vmap(jax.random.PRNGKey)(GAME_SEED + jnp.arange(games))
    r, i, alive = jax.jit(jax.vmap(one))(keys)
    # [games, points, horizon, sequences] -> [games, points, sequences, horizon]
    r, i = np.asarray(r), np.asarray(i).reshape(np.shape(r))
    return np.moveaxis(r, -1, -2), np.moveaxis(i, -1, -2), np.asarray(alive)


def scores(real: np.ndarray, imagined: np.ndarray, ks) -> dict:
    """The figures of the module's docstring from `[starts, sequences, horizon]` rewards."""
    out = {}
    for k in ks:
        r, i = real[..., :k].sum(-1), imagined[..., :k].sum(-1)
        rs, is_ = r[:, :STEER], i[:, :STEER]
        dr, di = rs - rs.mean(1, keepdims=True), is_ - is_.mean(1, keepdims=True)
        unique = (rs == rs.max(1, keepdims=True)).sum(1) == 1
        n = int(unique.sum())
        best_r, best_i = np.argmax(rs[unique], 1), np.argmax(is_[unique], 1)
        out[str(k)] = {
            "corr_all": float(np.corrcoef(r.ravel(), i.ravel())[0, 1]),
            "corr_steer": float(np.corrcoef(dr[unique].ravel(), di[unique].ravel())[0, 1]) if n else None,
            "best_steer_agree": float(np.mean(best_i == best_r)) if n else None,
            "starts_with_one_best": n,
            "best_share_real": (np.bincount(best_r, minlength=STEER) / max(1, n)).tolist(),
            "best_share_imagined": (np.bincount(best_i, minlength=STEER) / max(1, n)).tolist(),
            "mean_real": r.mean(0).tolist(),
            "mean_imagined": i.mean(0).tolist(),
            "accelerate_gap_real": float(np.mean(r[:, 3] - r[:, 0])),
            "accelerate_gap_imagined": float(np.mean(i[:, 3] - i[:, 0])),
        }
    return out


def probe(run_dir: str, games: int, every: int, horizon: int, ks) -> dict:
    from cdrl.models import make_variant
    from cdrl.runs.init_from import restore_params
    from cdrl.runs.rundir import RunDir
    from cdrl.runs.sources import run_game

    cfg, params, step = restore_params(RunDir(run_dir))
    variant = make_variant(cfg.variant, cfg.arch)
    if not variant.predicts_reward or cfg.data != "game":
        raise SystemExit(f"{run_dir}: needs a reward-predicting controller variant's run on the built-in game")
    game, env_params = run_game(cfg)
    real, imagined, alive = branch_returns(variant, params, game, env_params, horizon, every, games,
                                           cfg.episode_steps)
    real, imagined = real[alive], imagined[alive]
    return {"run": str(Path(run_dir)), "variant": cfg.variant, "preset": cfg.preset, "level": cfg.level,
            "step": step, "starts": int(len(real)), "by_steps": scores(real, imagined, ks)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", nargs="+", help="controller variants' runs on the built-in game")
    parser.add_argument("--games", type=int, default=32, help="games the privileged policy plays (default 32)")
    parser.add_argument("--every", type=int, default=10, help="steps between branch points (default 10)")
    parser.add_argument("--horizon", type=int, default=15, help="imagined steps (default 15, the critic's)")
    parser.add_argument("--ks", type=int, nargs="+", default=[1, 5, 15], help="steps the returns are summed over")
    parser.add_argument("--out", default=None, help="also write the JSON result to this file")
    args = parser.parse_args(argv)
    if max(args.ks) > args.horizon:
        parser.error(f"--ks {max(args.ks)} is beyond --horizon {args.horizon}")
    results = [probe(d, args.games, args.every, args.horizon, args.ks) for d in args.run_dirs]
    emit({"games": args.games, "every": args.every, "horizon": args.horizon, "explore": EXPLORE,
          "sequences": SEQUENCES, "results": results}, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
