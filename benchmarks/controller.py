"""The controller experiment (`cdrl.analysis.control`): model-based controllers, PPO at the same
and at ten times the game frames, and the reference policies, on the same held-out games.

Reported per configuration (`configs[name]`): its options, the game frames of a run, per seed
the final held-out `return` (mean over the games, with their 95 % CI), `length` (survival in
steps), the learning curve ([game frames, held-out return] after each evaluation), the seconds
it took, and for models with a reward head how well it predicts the reward of its own play on
the held-out games (`reward_fit`: correlation and R²), its predicted and real reward per step
and its next-frame excess ratio over the last quarter of training; across seeds the mean,
standard deviation and 95 % CI (Student t, n - 1 degrees of freedom) of each. `references`
holds the reference policies' rows (a CI over the games: there is no seed to vary).

Prints a table and ends with one JSON line (`--out FILE` also writes it there, after every
configuration with `"partial": true` until the last). Budgets: `--full` is the committed one
(small preset, 38 400 game frames per run, 5 seeds, 64 held-out games of at most 200 steps;
about 5 hours on 2 cores):

    .venv/bin/python benchmarks/controller.py --full --work-dir notebooks/runs/full/03_controller \\
        --out benchmarks/results/controller.json --figure benchmarks/results/controller.png

`--quick` is a smoke test (tiny preset, a few updates; says only that the script runs). Runs
are kept under `--work-dir`; a finished run is read back and an unfinished one resumed, so a
killed experiment continues where it stopped (notebook 03 reads the same runs).

`--merge A.json B.json ...` runs nothing: it pools result files of the same experiment run in
several invocations (other seeds, other configurations; `cdrl.analysis.control.merge` checks
that they share the budget and the held-out games) and recomputes the across-seed figures:

    .venv/bin/python benchmarks/controller.py --merge seeds01.json seed2.json --out result.json
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
from pathlib import Path

from common import emit, warn_if_busy


def main(argv=None) -> int:
    from cdrl.analysis.control import BUDGETS, CONFIGS, curves_figure, format_results, run_experiment

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--full", action="store_true", help="the committed budget (default: a short check)")
    size.add_argument("--quick", action="store_true", help="a smoke test on the tiny preset")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4], help="training seeds (default: 0-4)")
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS),
                        help="configurations to run, in this order (default: all)")
    parser.add_argument("--level", default="thesis", help="the game's level (envs.slither.LEVELS; default: thesis)")
    parser.add_argument("--preset", default=None,
                        help="the architecture preset (cdrl.models.PRESETS; default: the budget's, small for --full)")
    parser.add_argument("--work-dir", default=None, help="where the runs go (default: a temporary directory)")
    parser.add_argument("--out", default=None, help="also write the JSON result to this file")
    parser.add_argument("--figure", default=None, help="draw the learning curves into this PNG file")
    parser.add_argument("--merge", nargs="+", default=None, metavar="FILE",
                        help="run nothing: pool these result files (JSON) into one, the figures across seeds "
                             "recomputed")
    args = parser.parse_args(argv)
    if args.merge:
        return merge_files(args.merge, args.out, args.figure)
    import jax

    # Every seed of a configuration runs the same programs: compile each once.
    jax.config.update("jax_compilation_cache_dir", os.environ.get("JAX_COMPILATION_CACHE_DIR")
                      or tempfile.mkdtemp(prefix="cdrl-controller-xla-"))
    budget = BUDGETS["full" if args.full else "tiny" if args.quick else "default"]
    budget = dataclasses.replace(budget, level=args.level, preset=args.preset or budget.preset)
    work = Path(args.work_dir or tempfile.mkdtemp(prefix="cdrl-controller-"))
    load_start = os.getloadavg()[0]

    def partial(results: dict) -> None:
        print(format_results(results), file=sys.stderr, flush=True)
        if args.out:
            emit({**results, "partial": True}, args.out)

    results = run_experiment(args.configs, budget, args.seeds, work, on_config=partial)
    results["budget"]["name"] = "full" if args.full else "quick" if args.quick else "default"
    warn_if_busy(results, load_start, os.getloadavg()[0])
    if args.figure:
        from cdrl.analysis.plots import save_figure

        save_figure(curves_figure(results), Path(args.figure))
    emit(results, args.out)
    return 0


def merge_files(paths, out, figure) -> int:
    import json

    from cdrl.analysis.control import curves_figure, format_results, merge

    parts = []
    for path in paths:
        try:
            parts.append(json.loads(Path(path).read_text()))
        except (OSError, json.JSONDecodeError) as e:
            raise SystemExit(f"--merge: cannot read the result file {path}: {e}") from None
    try:
        results = merge(parts)
    except ValueError as e:
        raise SystemExit(f"--merge: {e}") from None
    results["merged_from"] = [str(p) for p in paths]
    print(format_results(results), file=sys.stderr, flush=True)
    if figure:
        from cdrl.analysis.plots import save_figure

        save_figure(curves_figure(results), Path(figure))
    emit(results, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
