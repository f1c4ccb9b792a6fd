"""Does training over a few imagined steps make a world model's imagination rank actions?

Per configuration of the ladder (each adds a loss of `cdrl.training.lookahead`) and seed, an
offline run of a controller variant (learner world_model) on the built-in game, then:

- the held-out excess ratio one step ahead (the run's final evaluation), and open loop at
  steps 1, 5 and 15 after 8 real frames (`cdrl.evaluation.multistep`);
- the imagination probe (`cdrl eval --imagination`, `cdrl.evaluation.imagination_probe`):
  whether the imagined H-step return plus the value ranks the steering choices as the game's
  15-step return does, the reward AUC per imagined step and the value's correlation;
- the cost per update: the median frames per second of the run's steps.

The ladder: `one_step` (teacher-forced, the look-ahead off), `frames` (+ the imagined frames'
BCE), `reward` (+ the reward head), `full` (+ the continuation and value heads).

    .venv/bin/python experiments/world_models/lookahead_study.py --work-dir DIR [--configs one_step full]
        [--seeds 0 1 2] [--variant final_proposal] [--level turned] [--steps 4000] [--out FILE]

A finished run in DIR is read back, an unfinished one resumed. Ends with one JSON line.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

if not __package__:  # run as a file, not with -m: the repository root on the path (benchmarks/, experiments/)
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import emit  # noqa: E402

OFF = {"imagined_frame_weight": 0.0, "reward_head_weight": 0.0, "cont_weight": 0.0, "value_weight": 0.0}
# name -> RunConfig options beside the study's
LADDER = {
    "one_step": {"lookahead_steps": 0},
    "frames": {**OFF, "imagined_frame_weight": 1.0},
    "reward": {**OFF, "imagined_frame_weight": 1.0, "reward_head_weight": 1.0},
    "full": {},
    # + the variant's reward error balanced over its sign classes (weight --balanced), on the real
    # steps, then on the imagined ones too
    "full_bal": {"reward_balanced_weight": None},
    "full_bal_imag": {"reward_balanced_weight": None, "imagined_reward_balanced_weight": None},
}
OPEN_LOOP_STEPS = (1, 5, 15)


def config_of(name: str, args, seed: int):
    from cdrl.runs.config import RunConfig

    return RunConfig(variant=args.variant, learner="world_model", preset="small", max_filter=args.max_filter,
                     level=args.level, steps=args.steps, seed=seed, eval_every=max(1, args.steps // 2),
                     checkpoint_every=max(1, args.steps // 2), tensorboard=False, head_grad=args.head_grad,
                     grad_clip=args.grad_clip, gamma=args.gamma, gae_lambda=args.lam, value_backup=args.value_backup,
                     frame_value_weight=args.frame_value, advantage_weight=args.advantage,
                     episodes=args.data_episodes,
                     data_policy=args.data_policy, mirror_streams=args.mirror_streams,
                     **options_of(name, args))


def options_of(name: str, args) -> dict:
    """Configuration `name`'s options beside the study's, the balanced weights filled in."""
    return {"lookahead_steps": args.lookahead_steps,
            **{k: args.balanced if v is None else v for k, v in LADDER[name].items()}}


def measure(run_dir: Path, args) -> dict:
    from cdrl.analysis.imagination_video import imagination_report
    from cdrl.analysis.report import load_run, restore_model, run_episodes
    from cdrl.evaluation.multistep import multistep_scores

    run = load_run(run_dir)
    model, (_, test) = restore_model(run), run_episodes(run, args.episodes)
    scores = multistep_scores(model.variant, model.params, test, 8, max(OPEN_LOOP_STEPS))
    fps = [r["fps"] for r in run.metrics[len(run.metrics) // 10:] if r.get("fps")]
    last = run.metrics[-1]["terms"]
    return {"run": str(run_dir), "step": model.step,
            "excess_ratio": run.evals[-1]["excess_ratio"],
            "open_loop": {str(k): scores["excess_ratio"][k - 1] for k in OPEN_LOOP_STEPS},
            "frames_per_second": float(np.median(fps)) if fps else None,
            "last_terms": last,
            "probe": imagination_report(run_dir, games=args.games, video=False)[0]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work-dir", required=True, help="where the runs go (one per configuration and seed)")
    parser.add_argument("--configs", nargs="+", default=list(LADDER), choices=list(LADDER))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--variant", default="final_proposal")
    parser.add_argument("--level", default="turned")
    parser.add_argument("--max-filter", type=int, default=5)
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--lookahead-steps", type=int, default=3)
    parser.add_argument("--head-grad", type=float, default=0.01)
    parser.add_argument("--balanced", type=float, default=0.003, help="full_bal, full_bal_imag: the balanced weight")
    parser.add_argument("--grad-clip", type=float, default=0.0, help="the model's global gradient norm clip (0: none)")
    parser.add_argument("--gamma", type=float, default=0.99, help="the value's discount (cdrl's --gamma)")
    parser.add_argument("--lam", type=float, default=0.95, help="the value's lambda (cdrl's --gae-lambda)")
    parser.add_argument("--value-backup", default="lambda", help="the value's targets (cdrl's --value-backup)")
    parser.add_argument("--frame-value", type=float, default=0.0,
                        help="the weight of the frame value head (cdrl's --frame-value-weight; 0: none)")
    parser.add_argument("--advantage", type=float, default=0.0,
                        help="the weight of the advantage head (cdrl's --advantage-weight; 0: none)")
    parser.add_argument("--data-policy", default="auto", help="the policy that plays the data (cdrl's --data-policy)")
    parser.add_argument("--mirror-streams", action="store_true", help="half of the streams see their episodes mirrored")
    parser.add_argument("--data-episodes", type=int, default=60, help="episodes the data set holds (cdrl's --episodes)")
    parser.add_argument("--episodes", type=int, default=6, help="held-out episodes scored open loop")
    parser.add_argument("--games", type=int, default=32, help="games of the imagination probe")
    parser.add_argument("--train-only", action="store_true", help="train (or resume) the runs, measure nothing")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    from cdrl.evaluation.stats import across
    from cdrl.runs.rundir import RunDir
    from cdrl.runs.train import train_run

    result = {"experiment": "lookahead_study", "variant": args.variant, "preset": "small",
              "max_filter": args.max_filter, "level": args.level, "steps": args.steps,
              "lookahead_steps": args.lookahead_steps, "head_grad": args.head_grad, "grad_clip": args.grad_clip,
              "gamma": args.gamma, "lam": args.lam, "value_backup": args.value_backup,
              "frame_value": args.frame_value, "advantage": args.advantage,
              "data_episodes": args.data_episodes, "data_policy": args.data_policy,
              "mirror_streams": args.mirror_streams, "configs": {}}
    for name in args.configs:
        rows = {}
        for seed in args.seeds:
            run_dir = Path(args.work_dir) / f"{args.variant}_{name}_s{seed}"
            start = time.perf_counter()
            cfg = config_of(name, args, seed)
            if not (RunDir(run_dir).path / "config.json").is_file():
                train_run(cfg, run_dir, progress=False)
            elif RunDir(run_dir).metrics.read()[-1]["step"] + 1 < args.steps:  # steps count from 0
                train_run(None, run_dir, resume=True, progress=False)
            if args.train_only:
                continue
            rows[seed] = {**measure(run_dir, args), "seconds": time.perf_counter() - start}
            print(name, seed, rows[seed]["excess_ratio"], rows[seed]["open_loop"], flush=True)
        if args.train_only:
            continue
        summary = {"excess_ratio": across([r["excess_ratio"] for r in rows.values()]),
                   "open_loop": {k: across([r["open_loop"][k] for r in rows.values()]) for k in rows[args.seeds[0]]
                                 ["open_loop"]}}
        result["configs"][name] = {"options": options_of(name, args), "seeds": rows, "summary": summary}
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
