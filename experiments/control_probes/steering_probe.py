"""Does a world model's state hold the steering? A linear controller cloned onto its core output.

The privileged policy (`envs.policies.privileged_policy`) plays `--games` training games (seeds
0, 1, ...; a fifth of its steps replaced by random turns, so that the data holds recoveries),
while the run's world model, teacher-forced on the frames and the buttons executed
(`followed_play`), gives its core output h_t at every step. Ridge regressions fit the privileged
policy's turn buttons at t + 1 (the step the controller's output at t acts in) from h_t, and, as
the reference, from the pixels of o_{t+1} (what the privileged choice at t + 1 was made on), on 85 % of the steps; the
rest give each probe's held-out accuracy. Then the probe on h, fitted on every step, plays as a
controller (turn buttons pressed where its output is above 0, accelerate never) on the control
experiment's 64 held-out games, beside never-accelerate and the privileged policy.

It measures what a controller that only reads the world model's features (`--controller real
--scope controller`) could reach if it learnt the privileged policy's choices with their answers
given, and so whether its features or its learning rule limit it.

    .venv/bin/python experiments/control_probes/steering_probe.py RUN_DIR [--games 128] [--out FILE]

RUN_DIR: a controller variant's run on the built-in game (an offline world model, `--controller
none`, or an online run). Ends with one JSON line.

The figures of its first runs (LOG.md, with their commit) came from older code. The exploration
draw was not yet `envs.policies.random_turns_instead`. The model was given, at o_t, the buttons
executed at o_{t-1}: one step behind its training. Their result files are deleted; a re-run
draws other exploratory steps and gives the model the buttons as trained.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

if not __package__:  # run as a file, not with -m: the repository root on the path (benchmarks/, experiments/)
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import emit  # noqa: E402

RIDGE = 10.0  # the probes' L2 penalty, on standardised inputs
EXPLORE = 0.2  # the share of the privileged policy's steps replaced by random turns
HELD_OUT = 0.15  # the share of the steps (the last games') each probe is scored on


def fit_ridge(x: np.ndarray, y: np.ndarray):
    """(mean, std, weights with a bias last) of ridge regression of the ±1 labels 2y - 1 on x."""
    mu, sd = x.mean(0), x.std(0) + 1e-6
    a = np.c_[(x - mu) / sd, np.ones(len(x))]
    w = np.linalg.solve(a.T @ a + RIDGE * np.eye(a.shape[1]), a.T @ (2.0 * y - 1.0))
    return mu, sd, w


def predict(fit, x: np.ndarray) -> np.ndarray:
    mu, sd, w = fit
    return np.c_[(x - mu) / sd, np.ones(len(x))] @ w


def collect(variant, params, game, env_params, games: int, max_steps: int):
    """Per game and step: h_t, the privileged policy's buttons, whether the game was on, and
    o_t at the model's resolution (`followed_play`: a fifth of the steps random turns)."""
    import jax
    import jax.numpy as jnp

    from experiments.control_probes.followed_play import follow_step, start

    body = follow_step(variant, params, game, env_params, EXPLORE)

    def one(key):
        return jax.lax.scan(body, start(variant, game, env_params, key), None, length=max_steps)[1]

    run = jax.jit(jax.vmap(one))

    return [np.asarray(x) for x in run(jax.vmap(jax.random.PRNGKey)(jnp.arange(games)))[:4]]  # not the rewards


def linear_controller(variant, params, fit):
    """The probe on h as a noise-free policy for `play`: the model steps on o_t and the buttons
    it pressed, and its turn buttons at t + 1 are pressed where the probe is above 0."""
    import jax.numpy as jnp

    from cdrl.data.frames import model_obs
    from cdrl.models.base import StepInput

    mu, sd, w = (jnp.asarray(x, jnp.float32) for x in fit)

    def init(key):
        del key
        return {"carry": variant.init_carry(1), "action": jnp.zeros((1, 3)), "is_first": jnp.ones((1,), bool)}

    def step(key, state, obs):
        del key
        x = StepInput(obs=model_obs(obs, variant.arch)[None], action=state["action"], is_first=state["is_first"])
        carry, _ = variant.step(params, state["carry"], x)
        z = jnp.concatenate([(variant.features(carry)[0] - mu) / sd, jnp.ones(1)]) @ w
        nxt = jnp.concatenate([(z > 0).astype(jnp.float32), jnp.zeros(1)])[None]
        return state["action"][0], {"carry": carry, "action": nxt, "is_first": jnp.zeros((1,), bool)}

    return init, step


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", help="a controller variant's run on the built-in game")
    parser.add_argument("--games", type=int, default=128, help="privileged games to fit on (default 128)")
    parser.add_argument("--out", default=None, help="also write the JSON result to this file")
    args = parser.parse_args(argv)
    from cdrl.evaluation.play import EVAL_SEED, compare_policies
    from cdrl.models import make_variant
    from cdrl.runs.init_from import restore_params
    from cdrl.runs.rundir import RunDir
    from cdrl.runs.sources import run_game

    cfg, params, step = restore_params(RunDir(args.run_dir))
    variant = make_variant(cfg.variant, cfg.arch)
    if not variant.has_controller or cfg.data != "game":
        raise SystemExit(f"{args.run_dir}: needs a controller variant's run on the built-in game")
    game, env_params = run_game(cfg)
    h, label, alive, frames = collect(variant, params, game, env_params, args.games, cfg.episode_steps)
    # h_t (having seen o_t and a_t) chooses the buttons of t + 1; o_{t+1} is what they were chosen on
    on = alive[:, 1:].reshape(-1)
    x_h = h[:, :-1].reshape(-1, h.shape[-1])[on]
    x_pixels = frames[:, 1:].reshape(len(on), -1)[on]
    y = label[:, 1:, :2].reshape(-1, 2)[on]
    cut = int((1.0 - HELD_OUT) * len(y))
    result = {"run": str(Path(args.run_dir)), "variant": cfg.variant, "preset": cfg.preset, "level": cfg.level,
              "step": step, "games": args.games, "steps": int(len(y)), "ridge": RIDGE,
              "turn_rate_held_out": y[cut:].mean(0).tolist()}
    for name, x in (("h", x_h), ("pixels", x_pixels)):
        fit = fit_ridge(x[:cut], y[:cut])
        result[f"accuracy_{name}"] = ((predict(fit, x[cut:]) > 0) == (y[cut:] > 0.5)).mean(0).tolist()
    init, policy_step = linear_controller(variant, params, fit_ridge(x_h, y))
    rows = compare_policies(game, env_params, {"linear_on_h": (init, policy_step)}, 64, cfg.episode_steps,
                            seed=EVAL_SEED)
    result["returns"] = {k: rows[k] for k in ("linear_on_h", "never_accelerate", "privileged")}
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
