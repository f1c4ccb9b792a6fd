"""Multi-step training against one-step training: how a model's predictions hold when it is
fed its own output.

Per curriculum (`cdrl train --multistep`: `1` is teacher forcing, `1,3,5` Oh et al.'s
curriculum over equal thirds of the steps) and seed, an offline run of `main` on the built-in
game (small preset, `fast` recipe, its 60 collected episodes), then the held-out excess ratio of
its predictions fed back for 15 steps after 8 real frames (`cdrl.evaluation.multistep`): step 1
is the one-step prediction, 1 at step k is as good as holding the last real frame k steps.

    .venv/bin/python experiments/world_models/multistep_training.py --work-dir DIR [--seeds 0 1 2] \\
        [--curricula 1 1,3,5] [--steps 4000] [--out FILE]

A finished run in DIR is read back, an unfinished one resumed. Ends with one JSON line: per
curriculum and seed the ratios at every step, and per curriculum the mean with a 95 % CI across
seeds at k = 1, 5, 10, 15
(`cdrl.evaluation.stats.across`).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

if not __package__:  # run as a file, not with -m: the repository root on the path (benchmarks/, experiments/)
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import emit  # noqa: E402

STEPS_REPORTED = (1, 5, 10, 15)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work-dir", required=True, help="where the runs go (one per curriculum and seed)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--curricula", nargs="+", default=["1", "1,3,5"], help="--multistep values")
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--episodes", type=int, default=6, help="held-out episodes scored")
    parser.add_argument("--context", type=int, default=8)
    parser.add_argument("--horizon", type=int, default=15)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    from cdrl.evaluation.stats import across
    from cdrl.analysis.report import load_run, restore_model, run_episodes
    from cdrl.evaluation.multistep import multistep_scores
    from cdrl.runs.config import RunConfig
    from cdrl.runs.rundir import RunDir
    from cdrl.runs.train import train_run

    result = {"benchmark": "multistep_training", "variant": "main", "preset": "small", "recipe": "fast",
              "steps": args.steps, "context": args.context, "horizon": args.horizon,
              "held_out_episodes": args.episodes, "curricula": {}}
    for curriculum in args.curricula:
        rows = {}
        for seed in args.seeds:
            run_dir = Path(args.work_dir) / f"k{curriculum.replace(',', '-')}_s{seed}"
            start = time.perf_counter()
            if not (RunDir(run_dir).path / "config.json").is_file():
                train_run(RunConfig(variant="main", preset="small", steps=args.steps, seed=seed, multistep=curriculum,
                                    eval_every=1000, checkpoint_every=1000), run_dir, progress=False)
            elif load_run(run_dir).metrics[-1]["step"] + 1 < args.steps:  # steps count from 0
                train_run(None, run_dir, resume=True, progress=False)
            run = load_run(run_dir)
            model, (_, test) = restore_model(run), run_episodes(run, args.episodes)
            scores = multistep_scores(model.variant, model.params, test, args.context, args.horizon)
            rows[seed] = {"run": str(run_dir), "step": model.step, "excess_ratio": scores["excess_ratio"],
                          "windows": scores["windows"], "seconds": time.perf_counter() - start}
            print(curriculum, seed, [round(scores["excess_ratio"][k - 1], 3) for k in STEPS_REPORTED], flush=True)
        result["curricula"][curriculum] = {
            "seeds": rows,
            "at": {str(k): across([r["excess_ratio"][k - 1] for r in rows.values()]) for k in STEPS_REPORTED}}
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
