"""Offline variants at the thesis's size: do the small preset's verdicts hold at 150 x 150 with
an LSTM of 512?

Per variant (default `main`, `baseline_ff`, `residual`, `closed_loop_minus`), at the thesis
preset and the `fast` recipe (4 streams x 8 frames a step, standardised input, FC init gain 5):
the thesis's learning-rate search over the seeds (`cdrl lr-search --seed ...`: a rate passes
only if no kernel's ||grad|| / ||param|| exceeds the threshold on any seed), then every seed
trained at the chosen rate as its own run (`cdrl train --seed S`: its own initialisation and its
own 60 collected behaviour-policy episodes of at most 200 steps, 6 held out; one run after
another, which on a CPU runs the thesis-sized convolutions faster than a vmapped sweep), then
every trained seed scored on its held-out episodes: the one-step excess ratio, and the model fed
its own predictions for `--horizon` steps after `--context` real frames
(`cdrl.evaluation.multistep`).

    .venv/bin/python experiments/world_models/thesis_variants.py --work-dir DIR [--steps 1000] [--seeds 0 1 2] \\
        [--variants main baseline_ff residual closed_loop_minus] [--out FILE]

A finished search or run in DIR is read back, an interrupted run resumed. Ends with one
JSON line: per variant the chosen rate and the search, per seed the held-out excess ratio and the
open-loop ratios, across seeds the mean with a 95 % CI at k = 1, 5, 15, and each variant's
paired difference from `main` seed by seed (a seed gives every variant the same data).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

if not __package__:  # run as a file, not with -m: the repository root on the path (benchmarks/, experiments/)
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import emit  # noqa: E402

STEPS_REPORTED = (1, 5, 15)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work-dir", required=True, help="where the searches and sweeps go (one per variant)")
    parser.add_argument("--variants", nargs="+", default=["main", "baseline_ff", "residual", "closed_loop_minus"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--preset", default="thesis", help="another preset for a quick check of the script")
    parser.add_argument("--steps", type=int, default=1000, help="training steps of 4 x 8 frames per seed")
    parser.add_argument("--candidates", type=float, nargs="+", default=[2.0, 1.5, 1.0])
    parser.add_argument("--probe-steps", type=int, default=30)
    parser.add_argument("--threshold", type=float, default=1.0)
    parser.add_argument("--episodes", type=int, default=6, help="held-out episodes scored")
    parser.add_argument("--data-episodes", type=int, default=60, help="episodes collected per seed (a tenth held out)")
    parser.add_argument("--episode-steps", type=int, default=200)
    parser.add_argument("--context", type=int, default=8)
    parser.add_argument("--horizon", type=int, default=15)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    from cdrl.evaluation.stats import across
    from cdrl.analysis.report import load_run, restore_model, run_episodes
    from cdrl.data.atomic import atomic_write_text
    from cdrl.evaluation.multistep import multistep_scores
    from cdrl.runs.config import RunConfig
    from cdrl.analysis.plots import held_out_ratios
    from cdrl.runs.sweep import lr_search
    from cdrl.runs.train import train_run

    work = Path(args.work_dir)
    work.mkdir(parents=True, exist_ok=True)
    data = dict(data="game", episodes=args.data_episodes, episode_steps=args.episode_steps)
    result = {"benchmark": "thesis_variants", "preset": args.preset, "recipe": "fast", "steps": args.steps,
              "frames_per_seed": args.steps * 32, "seeds": args.seeds, "context": args.context,
              "horizon": args.horizon, "held_out_episodes": args.episodes, "variants": {}}
    searches_file = work / "lr_search.json"
    searches = json.loads(searches_file.read_text()) if searches_file.exists() else {}
    for variant in args.variants:
        settings = {"candidates": args.candidates, "probe_steps": args.probe_steps, "threshold": args.threshold,
                    "seeds": args.seeds}
        if searches.get(variant, {}).get("settings") != settings:
            start = time.perf_counter()
            found = lr_search(RunConfig(variant=variant, preset=args.preset, **data), args.candidates, args.probe_steps,
                              args.threshold, progress=False, data_cache=work / "data-cache", seeds=args.seeds)
            searches[variant] = {"settings": settings, "result": found, "seconds": time.perf_counter() - start}
            atomic_write_text(searches_file, json.dumps(searches, indent=2) + "\n")
        lr = searches[variant]["result"]["chosen"]
        print(variant, "lr", lr, flush=True)
        if lr is None:
            result["variants"][variant] = {"lr": None, "lr_search": searches[variant]}
            continue
        per_seed = {}
        for seed in args.seeds:
            run_dir = work / variant / f"seed{seed}"
            start = time.perf_counter()
            entry = {"run": str(run_dir), "diverged": None}
            try:
                if not (run_dir / "config.json").is_file():
                    train_run(RunConfig(variant=variant, preset=args.preset, steps=args.steps, lr=lr, seed=seed,
                                        eval_every=args.steps // 4, eval_episodes=args.episodes,
                                        checkpoint_every=args.steps // 4, **data), run_dir, progress=False)
                elif load_run(run_dir).metrics[-1]["step"] + 1 < args.steps:  # steps count from 0
                    train_run(None, run_dir, resume=True, progress=False)
            except RuntimeError as exc:  # diverged: the run keeps its last good state
                entry["diverged"] = str(exc)
            run = load_run(run_dir)
            entry["steps"] = run.metrics[-1]["step"] + 1
            entry["seconds"] = time.perf_counter() - start
            if entry["diverged"] is None:
                entry["excess_ratio"] = float(held_out_ratios(run)[1][-1])
                model, (_, test) = restore_model(run), run_episodes(run, args.episodes)
                entry["open_loop"] = multistep_scores(model.variant, model.params, test, args.context,
                                                      args.horizon)["excess_ratio"]
            per_seed[str(seed)] = entry
            print(variant, seed, entry.get("excess_ratio"), entry.get("open_loop", [None])[:1], entry["diverged"],
                  flush=True)
        trained = [e for e in per_seed.values() if e["diverged"] is None]
        result["variants"][variant] = {
            "lr": lr, "lr_search": searches[variant], "per_seed": per_seed,
            "trained_seeds": len(trained),
            "excess_ratio": across([e["excess_ratio"] for e in trained]) if trained else None,
            "open_loop_at": {str(k): across([e["open_loop"][k - 1] for e in trained]) for k in STEPS_REPORTED
                             if k <= args.horizon} if trained else None}
    ref = result["variants"].get("main", {}).get("per_seed", {})
    for variant, entry in result["variants"].items():
        if variant == "main" or not entry.get("per_seed"):
            continue
        both = [s for s, e in entry["per_seed"].items() if e["diverged"] is None
                and s in ref and ref[s]["diverged"] is None]
        if both:
            entry["minus_main"] = across([entry["per_seed"][s]["excess_ratio"] - ref[s]["excess_ratio"] for s in both])
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
