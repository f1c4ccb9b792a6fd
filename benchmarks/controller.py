"""The controller experiment: model-based controllers, PPO and the reference policies on the same
held-out games of the built-in game.

Every configuration is a `cdrl train` run (`cdrl.runs.train.train_run`), trained once per seed
(`--seeds`; a seed sets the initialisation, the exploration and the training games), scored
`--evals` times during training and at the end on the same held-out games (seeds 10000,
10001, ...; `cdrl.evaluation.play.compare_policies`), noise-free: the controller executes ã,
PPO its greedy buttons. The reference policies (uniform random, random turning that never
accelerates, the thesis's behaviour switching, the privileged scripted policy) play the same
games once: they do not learn.

Configurations (`CONFIGS`; `--configs` picks some), each at the same number of game frames
(`steps` x B x T) unless named otherwise:
  critic        final_proposal, actor-critic in imagination (`--controller critic`)
  imagine       final_proposal, reward ascent through imagined rollouts (`--controller imagine`)
  rollout       final_proposal, the thesis's reward ascent through the real chunk, scope controller
  rollout-all   the same, scope all (the thesis's literal wording: may the model hallucinate reward?)
  critic-open   reward_prediction (open loop on observations), actor-critic in imagination:
                against `critic`, does closed loop − help?
  ppo           PPO at the same game frames
  ppo-10x       PPO at ten times the game frames

Reported per configuration (`configs[name]`): the recipe's options, the game frames of a run,
per seed the final `return` (mean over the held-out games, with their 95 % CI), `length` (mean
survival in steps), the learning curve (held-out return after each evaluation's game frames)
and, for models with a reward head, how well it predicts the reward of its own play on the
held-out games (`cdrl.evaluation.play.reward_fit`: correlation and R²); across seeds the
mean, standard deviation and 95 % CI (Student t, n - 1 degrees of freedom) of the final return
and survival. `references` holds the reference policies' rows. `--figure FILE` draws the
learning curves (mean over seeds with the 95 % CI band) against the references.

Prints a table and ends with one JSON line (`--out FILE` also writes it there).
Budgets: `--full` is the committed one (about 5 hours on 2 cores):

    .venv/bin/python benchmarks/controller.py --full --out benchmarks/results/controller.json \\
        --figure benchmarks/results/controller.png

`--quick` is a smoke test (tiny preset, a few updates, says only that the script runs).
Runs are kept under `--work-dir` and a finished run is not trained again, so a killed
experiment continues where it stopped; `--out` holds the finished configurations after each
one (`"partial": true` until the last).
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.stats

from common import emit, warn_if_busy

# name -> options of `cdrl train` (RunConfig fields) besides the budget's
CONFIGS: dict[str, dict] = {
    "critic": {"variant": "final_proposal", "controller": "critic", "optimizer": "adam", "lr": 1e-3},
    "imagine": {"variant": "final_proposal", "controller": "imagine", "optimizer": "adam", "lr": 1e-3},
    "rollout": {"variant": "final_proposal", "controller": "rollout", "scope": "controller"},
    "rollout-all": {"variant": "final_proposal", "controller": "rollout", "scope": "all"},
    "critic-open": {"variant": "reward_prediction", "controller": "critic", "optimizer": "adam", "lr": 1e-3},
    "ppo": {"variant": "ppo"},
    "ppo-10x": {"variant": "ppo", "frames_factor": 10},
}
# Model-based runs collect B 8 x T 16 game frames per update, PPO B 16 x T 32.
BUDGETS = {
    "full": {"preset": "small", "frames": 38_400, "eval_episodes": 64, "episode_steps": 200, "evals": 4,
             "warmup_steps": 50},
    "default": {"preset": "small", "frames": 6_400, "eval_episodes": 16, "episode_steps": 200, "evals": 2,
                "warmup_steps": 10},
    "quick": {"preset": "tiny", "frames": 256, "eval_episodes": 3, "episode_steps": 20, "evals": 1,
              "warmup_steps": 1},
}
SHAPES = {"ppo": (16, 32), "model": (8, 16)}


def across(values: list[float]) -> dict:
    """Mean, standard deviation (ddof 1) and 95 % CI (Student t, n - 1 dof) over seeds."""
    n = len(values)
    mean = float(np.mean(values))
    if n < 2:
        return {"mean": mean, "std": None, "ci95": None, "per_seed": list(values)}
    std = float(np.std(values, ddof=1))
    half = float(scipy.stats.t.ppf(0.975, n - 1) * std / np.sqrt(n))
    return {"mean": mean, "std": std, "ci95": [mean - half, mean + half], "per_seed": list(values)}


def run_config(name: str, options: dict, budget: dict, seed: int, work: Path) -> dict:
    """Train (or read back, when finished) one seed of a configuration; its figures."""
    from cdrl.evaluation.play import reward_fit
    from cdrl.models import make_variant
    from cdrl.runs.config import RunConfig
    from cdrl.runs.online import learner, model_params
    from cdrl.runs.rundir import RunDir
    from cdrl.runs.train import train_run

    options = dict(options)
    factor = options.pop("frames_factor", 1)
    batch, unroll = SHAPES["ppo" if options["variant"] == "ppo" else "model"]
    if budget["preset"] == "tiny":
        batch, unroll = 4, 4
    steps = max(1, budget["frames"] * factor // (batch * unroll))
    cfg = RunConfig(preset=budget["preset"], batch=batch, unroll=unroll, steps=steps, seed=seed,
                    eval_every=max(1, steps // budget["evals"]), checkpoint_every=max(1, steps // budget["evals"]),
                    eval_episodes=budget["eval_episodes"], episode_steps=budget["episode_steps"],
                    warmup_steps=budget["warmup_steps"], tensorboard=False, **options)
    run_dir = work / name / f"seed{seed}"
    run = RunDir(run_dir)
    t0 = time.perf_counter()
    finished = run.has_run() and any(r["step"] == steps for r in run.evals.read())
    if run.has_run() and not finished:  # a killed experiment: continue the run
        train_run(None, run_dir, resume=True)
    elif not finished:
        train_run(cfg, run_dir)
    wall = time.perf_counter() - t0
    evals = [r for r in run.evals.read() if r.get("split") == "play"]
    learned = "ppo" if cfg.variant == "ppo" else "controller"
    final = evals[-1]["policies"]
    out = {"return": final[learned]["mean_return"], "ci95_over_games": final[learned]["ci95"],
           "length": final[learned]["mean_length"], "wall_s": wall, "steps": steps,
           "frames": steps * batch * unroll,
           "curve": [[r["step"] * batch * unroll, r["policies"][learned]["mean_return"]] for r in evals],
           "references": {k: v for k, v in final.items() if k != learned}}
    cfg = run.read_config()
    if cfg.variant != "ppo" and make_variant(cfg.variant, cfg.arch).predicts_reward:
        import jax

        setup, fresh, _ = learner(cfg)
        state, _, _ = run.read_checkpoints().restore_latest_good(jax.eval_shape(fresh))
        variant, game, env_params = setup[0], setup[1], setup[2]
        params = model_params(state)
        seeds = np.arange(10_000, 10_000 + budget["eval_episodes"])
        out["reward_fit"] = reward_fit(variant, params, game, env_params, seeds, budget["episode_steps"])
    return out


def figure(results: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5))
    for name, r in results["configs"].items():
        curves = [s["curve"] for s in r["seeds"].values()]
        n = min(len(c) for c in curves)
        frames = np.array([c[i][0] for i in range(n) for c in curves[:1]])
        values = np.array([[c[i][1] for i in range(n)] for c in curves])
        mean = values.mean(axis=0)
        ax.plot(frames, mean, marker="o", label=f"{name} ({len(curves)} seeds)")
        if len(curves) > 1:
            half = scipy.stats.t.ppf(0.975, len(curves) - 1) * values.std(axis=0, ddof=1) / np.sqrt(len(curves))
            ax.fill_between(frames, mean - half, mean + half, alpha=0.2)
    for name, row in results["references"].items():
        ax.axhline(row["mean_return"], linestyle="--", linewidth=1, color="grey")
        ax.annotate(name, (ax.get_xlim()[0], row["mean_return"]), fontsize=8, va="bottom")
    ax.set_xscale("log")
    ax.set_xlabel("game frames of training")
    ax.set_ylabel(f"held-out return ({results['budget']['eval_episodes']} games, mean over seeds, 95 % CI)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--full", action="store_true", help="the committed budget (default: a short check)")
    size.add_argument("--quick", action="store_true", help="a smoke test on the tiny preset")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4], help="training seeds (default: 0-4)")
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS),
                        help="configurations to run (default: all)")
    parser.add_argument("--work-dir", default=None, help="where the runs go (default: a temporary directory)")
    parser.add_argument("--out", default=None, help="also write the JSON result to this file")
    parser.add_argument("--figure", default=None, help="draw the learning curves into this PNG file")
    args = parser.parse_args(argv)
    import jax

    jax.config.update("jax_compilation_cache_dir", os.environ.get("JAX_COMPILATION_CACHE_DIR")
                      or tempfile.mkdtemp(prefix="cdrl-controller-xla-"))
    budget_name = "full" if args.full else "quick" if args.quick else "default"
    budget = BUDGETS[budget_name]
    work = Path(args.work_dir or tempfile.mkdtemp(prefix="cdrl-controller-"))
    load_start = os.getloadavg()[0]
    results = {"budget": {"name": budget_name, **budget, "seeds": args.seeds, "level": "thesis"}, "configs": {},
               "references": None}
    for name in args.configs:
        seeds = {}
        for seed in args.seeds:
            seeds[str(seed)] = run_config(name, CONFIGS[name], budget, seed, work)
            print(f"{name} seed {seed}: return {seeds[str(seed)]['return']:.3f}", file=sys.stderr, flush=True)
        results["references"] = results["references"] or seeds[str(args.seeds[0])]["references"]
        row = {"options": CONFIGS[name], "frames": seeds[str(args.seeds[0])]["frames"], "seeds": seeds,
               "return": across([s["return"] for s in seeds.values()]),
               "length": across([s["length"] for s in seeds.values()])}
        fits = [s["reward_fit"] for s in seeds.values() if "reward_fit" in s]
        if fits:
            row["reward_fit"] = {k: across([f[k] for f in fits]) for k in ("correlation", "r2")}
        results["configs"][name] = row
        if args.out:  # what is done so far, should the experiment be stopped
            emit({**results, "partial": True}, args.out)
    lines = [f"held-out return over {budget['eval_episodes']} games, across seeds {args.seeds}: "
             "mean [95% CI, Student t]; survival in steps",
             f"{'policy':14s} {'frames':>9s} {'mean':>8s} {'95% CI across seeds':>22s} {'survival':>9s}   per seed"]
    for name, r in results["configs"].items():
        ci = r["return"]["ci95"] or [float("nan")] * 2
        lines.append(f"{name:14s} {r['frames']:9d} {r['return']['mean']:8.3f} [{ci[0]:8.3f}, {ci[1]:8.3f}] "
                     f"{r['length']['mean']:9.1f}   " + ", ".join(f"{v:.2f}" for v in r["return"]["per_seed"]))
    for name, row in results["references"].items():
        lines.append(f"{name:14s} {'-':>9s} {row['mean_return']:8.3f} [{row['ci95'][0]:8.3f}, {row['ci95'][1]:8.3f}] "
                     f"{row['mean_length']:9.1f}   (95% CI over the games; no seed to vary)")
    print("\n".join(lines), file=sys.stderr)
    warn_if_busy(results, load_start, os.getloadavg()[0])
    if args.figure:
        figure(results, args.figure)
    emit(results, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
