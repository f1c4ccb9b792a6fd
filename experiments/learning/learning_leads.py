"""Why `main` learnt slowly, lead by lead: held-out excess-ratio curves from vmapped sweeps.

Each row is one `cdrl sweep` (`cdrl.runs.sweep.sweep_run`): its configurations (seeds, and
learning rates where a row sweeps them) train as one vmapped program on the built-in game's
behaviour data (small preset), with held-out evaluations every `--eval-frames` training
frames. The rows walk from the thesis's recipe to the `fast` recipe one change at a time
(`path-*`), then try other leads on top of `fast` (`alt-*`) and take single changes back out
of it (`ablate-*`). Every row trains the same
number of frames, so curves compare per frame seen; seconds are in each configuration's
metrics (fps) and in experiments/learning/time_to_quality.py.

    .venv/bin/python experiments/learning/learning_leads.py --out experiments/learning/results/learning_leads.json \\
        --figure experiments/learning/results/learning_leads.png
    .venv/bin/python experiments/learning/learning_leads.py --rows path-thesis path-fast --frames 4096 --quick

The JSON line holds, per row and configuration, the curve (frames, excess ratio), the ratio
at the end and the frames at which it first fell below 1; and per row the mean and min/max
over its seeds.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from cdrl.analysis.plots import held_out_ratios, save_figure
from cdrl.analysis.report import load_run
from cdrl.runs.config import RunConfig
from cdrl.runs.sweep import Grid, sweep_run

if not __package__:  # run as a file, not with -m: the repository root on the path (benchmarks/, experiments/)
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import emit  # noqa: E402

# name -> (what changes, RunConfig options, grid); a grid without seeds takes --seeds, the
# alternatives on top of `fast` take seed 0 only (a lead, not a verdict).
ROWS: dict[str, tuple[str, dict, dict]] = {
    "path-thesis": ("the thesis's recipe: SGD lr 0.1, momentum 0.9, B 1, T 32, raw input", dict(recipe="thesis"), {}),
    "path-batch4": ("+ B 4 streams per step", dict(recipe="thesis", batch=4), {}),
    "path-std": ("+ standardised encoder input (obs_norm data)", dict(recipe="thesis", batch=4, obs_norm="data"), {}),
    "path-lr": ("+ learning rate 0.5, 1, 2 (one program; seeds 0, 1)", dict(recipe="thesis", batch=4, obs_norm="data"),
                dict(lr=(0.5, 1.0, 2.0), seed=(0, 1))),
    "path-gain": ("+ FC init gain 5 (lr 2)", dict(recipe="thesis", batch=4, obs_norm="data", lr=2.0,
                                                 fc_init_gain=5.0), {}),
    "path-fast": ("+ T 8: four times the updates per frame (= the fast recipe)", dict(recipe="fast"), {}),
    "alt-lr": ("fast, with lr 1 or 3 (one program)", dict(recipe="fast"), dict(lr=(1.0, 3.0), seed=(0,))),
    "ablate-std": ("fast without the standardised input (raw [0, 1] brightness)", dict(recipe="fast", obs_norm="none"), {}),
    "ablate-gain": ("fast without the FC init gain (gain 1)", dict(recipe="fast", fc_init_gain=1.0), {}),
    "alt-adam": ("fast, with Adam lr 1e-4, 3e-4, 1e-3 (one program) instead of SGD",
                 dict(recipe="fast", optimizer="adam"), dict(lr=(1e-4, 3e-4, 1e-3), seed=(0,))),
    "alt-clip": ("fast, with the global gradient norm clipped at 1 or 0.3", dict(recipe="fast"),
                 dict(grad_clip=(1.0, 0.3), seed=(0,))),
    "alt-cosine": ("fast, with warm-up (100 steps) and cosine decay over the budget",
                   dict(recipe="fast", lr_schedule="cosine", lr_warmup=100), dict(seed=(0,))),
    "alt-t4": ("fast, with T 4", dict(recipe="fast", unroll=4), dict(seed=(0,))),
}


def _parse(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--frames", type=int, default=65536, help="training frames per configuration (default: 65536)")
    p.add_argument("--eval-frames", type=int, default=8192, help="frames between held-out evaluations")
    p.add_argument("--episodes", type=int, default=60)
    p.add_argument("--episode-steps", type=int, default=200)
    p.add_argument("--runs", default="runs/learning-leads", help="where the sweeps' run directories go")
    p.add_argument("--quick", action="store_true", help="tiny preset, few episodes: a smoke run")
    p.add_argument("--out", default=None, help="also write the JSON line to this file")
    p.add_argument("--figure", default=None, help="write the curves (mean over seeds, min-max band) here")
    p.add_argument("--replot", default=None, metavar="JSON", help="only redraw --figure from a result file")
    return p.parse_args(argv)


def run_row(name: str, args) -> dict:
    what, options, grid = ROWS[name]
    preset = "tiny" if args.quick else "small"
    probe = RunConfig(preset=preset, **options)
    frames_per_step = probe.batch * probe.unroll
    steps = max(1, args.frames // frames_per_step)
    eval_every = max(1, args.eval_frames // frames_per_step)
    base = RunConfig(variant="main", preset=preset, episodes=args.episodes, episode_steps=args.episode_steps,
                     steps=steps, eval_every=eval_every, eval_episodes=6, checkpoint_every=steps, **options)
    out = Path(args.runs) / name
    if out.exists():
        shutil.rmtree(out)
    t0 = time.perf_counter()
    rows = sweep_run(base, Grid(**{"seed": tuple(args.seeds), **grid}), out, progress=False)
    seconds = time.perf_counter() - t0
    configs = []
    for row in rows:
        run = load_run(row["run_dir"])
        frames, ratios = held_out_ratios(run)
        below = frames[ratios < 1.0]
        configs.append({"name": row["name"], "seed": row["seed"], "lr": row["lr"],
                        **{k: row[k] for k in ("grad_clip",) if grid.get(k)},
                        "frames": frames.tolist(), "ratio": ratios.tolist(),
                        "ratio_at_end": row["test_excess_ratio"], "test_bce": row["test_bce"],
                        "frames_to_1": float(below[0]) if below.size else None,
                        "diverged_at": row["diverged_at"],
                        "fps": float(np.median([m["fps"] for m in run.metrics[1:]])) if len(run.metrics) > 1 else None})
    groups: dict[str, list[dict]] = {}
    for c in configs:
        key = ", ".join(f"{k} {c[k]:g}" for k in ("lr", "grad_clip") if k in c and grid.get(k))
        groups.setdefault(key or "-", []).append(c)
    summary = []
    for key, cs in groups.items():
        end = [c["ratio_at_end"] for c in cs if c["ratio_at_end"] is not None]
        to1 = [c["frames_to_1"] for c in cs]
        summary.append({"setting": key, "seeds": [c["seed"] for c in cs],
                        "ratio_at_end_mean": float(np.mean(end)) if end else None,
                        "ratio_at_end_min": float(np.min(end)) if end else None,
                        "ratio_at_end_max": float(np.max(end)) if end else None,
                        "frames_to_1": to1})
    print(f"{name}: {what}: " + "; ".join(
        f"{s['setting']} ratio {s['ratio_at_end_mean']:.3f} [{s['ratio_at_end_min']:.3f}, {s['ratio_at_end_max']:.3f}]"
        for s in summary if s["ratio_at_end_mean"] is not None), file=sys.stderr, flush=True)
    return {"row": name, "change": what, "options": options,
            "grid": {k: list(v) for k, v in grid.items() if k != "seed"}, "seeds": [c["seed"] for c in configs],
            "preset": preset, "batch": base.batch, "unroll": base.unroll, "steps": steps,
            "frames": steps * frames_per_step, "sweep_seconds": seconds, "groups": summary, "configs": configs}


def figure(result: dict, path: Path) -> None:
    """Two panels: the path from the thesis's recipe to fast, then the alternatives and the
    ablations (with the fast curve repeated for reference). Mean over seeds, min-max band; a
    configuration that diverged is left out of its curve and named in the legend."""
    from matplotlib.figure import Figure

    rows = {row["row"]: row for row in result["rows"]}
    panels = [("the path from the thesis's recipe to fast", [n for n in rows if n.startswith("path-")]),
              ("on top of fast: alternatives and ablations",
               (["path-fast"] if "path-fast" in rows else []) + [n for n in rows if not n.startswith("path-")])]
    panels = [(title, names) for title, names in panels if names]
    fig = Figure(figsize=(7.0 * len(panels), 6.0))
    for k, (title, names) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), k + 1)
        i = 0
        for name in names:
            row = rows[name]
            by_setting: dict[str, list[dict]] = {}
            for c in row["configs"]:
                key = ", ".join(f"{g} {c[g]:g}" for g in ("lr", "grad_clip") if g in c and row["grid"].get(g))
                by_setting.setdefault(key, []).append(c)
            for key, cs in by_setting.items():
                label = name + (f" ({key})" if key else "")
                live = [c for c in cs if c["diverged_at"] is None]
                if len(live) < len(cs):
                    label += ", diverged at step " + ", ".join(str(c["diverged_at"]) for c in cs if c not in live)
                n = min((len(c["frames"]) for c in live), default=0)
                style = dict(color=f"C{i % 10}", ls="-" if i < 10 else "--")
                i += 1
                if n == 0:
                    ax.plot([], [], label=label, **style)
                    continue
                x = np.asarray(live[0]["frames"][:n])
                ys = np.array([c["ratio"][:n] for c in live])
                ax.plot(x, ys.mean(0), label=label + (f" [{len(live)} seeds]" if len(live) > 1 else ""), **style)
                if len(live) > 1:
                    ax.fill_between(x, ys.min(0), ys.max(0), color=style["color"], alpha=0.15)
        ax.axhline(1.0, color="black", lw=1, ls=":")
        ax.set_yscale("log")
        ax.set_ylim(0.5, 3.0)
        ax.set_xlabel("training frames")
        ax.set_ylabel("held-out excess ratio (1: copy last frame)")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize="x-small")
    fig.suptitle(f"main, {result['preset']} preset, built-in game ({result['episodes']} episodes of at most "
                 f"{result['episode_steps']} steps); mean over seeds, band min-max")
    fig.tight_layout()
    save_figure(fig, path)


def main(argv=None) -> int:
    args = _parse(argv)
    if args.replot:
        figure(json.loads(Path(args.replot).read_text()), Path(args.figure))
        return 0
    if args.quick:
        args.frames, args.eval_frames, args.episodes, args.episode_steps = 256, 128, 6, 30
    result = {"benchmark": "learning_leads", "variant": "main", "preset": "tiny" if args.quick else "small",
              "data": "built-in game, behaviour switching, level thesis", "episodes": args.episodes,
              "episode_steps": args.episode_steps, "seeds": args.seeds, "frames_per_config": args.frames,
              "cpu_count": os.cpu_count(), "load_avg_start": os.getloadavg()[0], "rows": []}
    for name in args.rows:
        result["rows"].append(run_row(name, args))
    result["load_avg_end"] = os.getloadavg()[0]
    if args.figure:
        figure(result, Path(args.figure))
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
