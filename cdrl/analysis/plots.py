"""The thesis's figures (chapter 5) for one or more run directories, as PNG files.

`plot_runs(run_dirs, out_dir)` writes, into `out_dir` (default `run_dirs[0]/plots`):

- `loss.png`: training loss of every run, running average over 4096 samples (figs 5.1/5.3/5.7/5.8);
- `excess.png`: held-out excess ratio (BCE - floor) / (copy-last BCE - floor) at every
  evaluation of every run (below 1: better than copying the last frame);
- `ratios.png`: ||grad||/||param|| of chosen parameter groups, running average over 256 steps
  (figs 5.4/5.5);
- `code_error.png`: code-prediction error MSE(d_t, k_t) over training, for runs that log it (fig 5.6);
- `prediction_<run>.png`: input frame, predicted next frame, true next frame, difference (fig 5.2);
- `rollout_<run>.png`: an open-loop rollout fed with the model's own predictions (these two
  figures: `cdrl.analysis.frame_figures`);
- `bce_bars.png`: train vs held-out BCE per run, with the copy-last-frame baseline (fig 5.9);
- `open_loop.png`: the held-out excess ratio at every step of predictions fed back for 15 steps
  (`cdrl.evaluation.multistep`), every run, against copying the last real frame as long.

Every figure has a fixed size in inches (the `*_SIZE` constants and functions) at `DPI`, so a
figure's pixel size is known in advance. Files appear atomically (`cdrl.data.atomic`: a
temporary file in the same directory, then a rename). Matplotlib's object API is used
directly, without pyplot, so no global backend state is touched.
"""
from __future__ import annotations

import itertools
import re
from pathlib import Path
from typing import Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

# The figures of a model's predicted frames live in cdrl.analysis.frame_figures; named here too, as every
# other figure is.
from cdrl.analysis.frame_figures import (PREDICTION_SIZE, Rollout, error_range, frame_range,  # noqa: F401
                                  open_loop_predictions, prediction_figure, rollout_figure, rollout_size)
from cdrl.analysis.report import (Run, evaluate_model, load_run, restore_model, run_episodes, running_mean,
                                  training_loss)
from cdrl.data.atomic import atomic_write
from cdrl.evaluation.metrics import excess_ratio
from cdrl.evaluation.multistep import multistep_scores
from cdrl.runs.checkpoint import CheckpointError
from cdrl.runs.rundir import RunDir

DPI = 100
LOSS_SIZE = (8.0, 5.0)
CODE_ERROR_SIZE = (8.0, 5.0)
OPEN_LOOP_STEPS = 15  # the open-loop figure's horizon (shorter where the episodes are)
# The thesis's monitored groups: encoder layer 4 kernel and decoder layer 3 kernel (0-based names).
DEFAULT_RATIO_GROUPS = ("obs_enc/conv3/kernel", "obs_dec/deconv2/kernel")
RATIO_WINDOW = 256


def ratios_size(n_groups: int) -> tuple[float, float]:
    return (5.0 * n_groups, 4.5)


def bars_size(n_runs: int) -> tuple[float, float]:
    return (max(6.0, 2.0 + 1.8 * n_runs), 5.0)


def save_figure(fig: Figure, path: Path) -> Path:
    """Write `fig` as a PNG at `DPI` to `path` atomically: readers see the old file or the
    complete new one, never a partial one."""
    FigureCanvasAgg(fig)
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=DPI), mode=0o644)
    return path


def _safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name) or "run"


def file_stems(runs: Sequence[Run]) -> list[str]:
    """A distinct file-name-safe name per run (its directory name, numbered if repeated)."""
    names = [_safe_name(r.name) for r in runs]
    return [n if names.count(n) == 1 else f"{n}-{i}" for i, n in enumerate(names)]


# ---------------------------------------------------------------- curves from the logs


def _styles():
    """Line styles per run, so that runs with overlapping curves stay distinguishable."""
    return itertools.cycle(["-", "--", "-.", ":"])


def _log_axes(fig: Figure, ax, xlabel: str, ylabel: str, title: str) -> Figure:
    """Finish a one-panel figure with a log y axis, labels, grid and legend."""
    ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    return fig


def loss_figure(runs: Sequence[Run]) -> Figure:
    """Training next-frame BCE of every run against training samples (frames) seen, each a
    running average over the previous 4096 samples (thesis figures 5.1, 5.3, 5.7, 5.8)."""
    fig = Figure(figsize=LOSS_SIZE)
    ax = fig.add_subplot()
    for run, style in zip(runs, _styles()):
        steps, loss = training_loss(run)
        ax.plot((steps + 1) * run.samples_per_step, running_mean(loss, run.loss_window), style, label=run.label)
    return _log_axes(fig, ax, "training samples (frames)", "training BCE per pixel",
                     "Training loss (running average over 4096 samples)")


_LAYER = re.compile(r"^(.*?)(\d+)(/kernel|/bias)$")


def resolve_groups(requested: Sequence[str] | None, available: set[str]) -> list[str]:
    """The parameter groups to plot. Explicit `requested` groups must exist. The default
    groups fall back, for a smaller preset, to the deepest layer of the same kind at or
    below the requested index (e.g. `obs_enc/conv3/kernel` -> `obs_enc/conv2/kernel`)."""
    if requested is not None:
        missing = [g for g in requested if g not in available]
        if missing:
            raise ValueError(f"no run logs the norm ratio of {missing}; available groups: {sorted(available)}")
        return list(requested)
    groups = []
    for group in DEFAULT_RATIO_GROUPS:
        match = _LAYER.match(group)
        prefix, index, suffix = match.group(1), int(match.group(2)), match.group(3)
        candidates = [int(m.group(2)) for m in map(_LAYER.match, available)
                      if m and m.group(1) == prefix and m.group(3) == suffix and int(m.group(2)) <= index]
        if candidates:
            groups.append(f"{prefix}{max(candidates)}{suffix}")
    if not groups:
        raise ValueError(f"none of the default groups {DEFAULT_RATIO_GROUPS} exist; pass groups= from {sorted(available)}")
    return groups


def ratios_figure(runs: Sequence[Run], groups: Sequence[str] | None = None) -> Figure:
    """Norm ratio ||grad|| / ||param|| of each chosen parameter group (one subplot per group,
    every run on it), running average over 256 steps (thesis figures 5.4, 5.5: the encoder's
    layer-4 kernel and the decoder's layer-3 kernel). Ratios >> 1 mean divergence."""
    available = {g for run in runs for m in run.metrics for g in m.get("ratios", {})}
    groups = resolve_groups(groups, available)
    fig = Figure(figsize=ratios_size(len(groups)))
    axes = fig.subplots(1, len(groups), squeeze=False)[0]
    for ax, group in zip(axes, groups):
        for run, style in zip(runs, _styles()):
            points = [(m["step"], m["ratios"][group]) for m in run.metrics if group in m.get("ratios", {})]
            if points:
                steps, values = np.array(points).T
                ax.plot(steps, running_mean(values, RATIO_WINDOW), style, label=run.label)
        ax.set_yscale("log")
        ax.set_xlabel("training step")
        ax.set_ylabel("||grad|| / ||param||")
        ax.set_title(group)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize="small")
    fig.suptitle(f"Norm ratios (running average over {RATIO_WINDOW} steps)")
    fig.tight_layout()
    return fig


def held_out_ratios(run: Run) -> tuple[np.ndarray, np.ndarray]:
    """(training frames seen, held-out excess ratio) of every evaluation in `eval.jsonl`."""
    points = [(e["step"] * run.samples_per_step,
               excess_ratio(e["bce"], e["copy_bce"], e["target_entropy"]))
              for e in run.evals if e.get("split") == "test" and "bce" in e]
    frames, ratios = (np.array(v, np.float64) for v in zip(*points)) if points else (np.zeros(0), np.zeros(0))
    return frames, ratios


def excess_figure(runs: Sequence[Run]) -> Figure:
    """Held-out excess ratio (BCE - floor) / (copy-last BCE - floor) of every run at each of
    its evaluations, against training frames seen; below the line at 1 a model beats copying
    the last frame."""
    fig = Figure(figsize=LOSS_SIZE)
    ax = fig.add_subplot()
    for run, style in zip(runs, _styles()):
        frames, ratios = held_out_ratios(run)
        if frames.size:
            ax.plot(frames, ratios, style, marker="o", ms=3, label=run.label)
    ax.axhline(1.0, color="black", lw=1, ls=":", label="copy last frame")
    return _log_axes(fig, ax, "training samples (frames)", "held-out excess ratio",
                     "(BCE - entropy floor) / (copy-last BCE - entropy floor), held-out frames")


def open_loop_figure(runs: Sequence[Run], scores: Sequence[dict]) -> Figure:
    """The held-out excess ratio at steps 1 .. K of open-loop prediction (`multistep_scores`
    of each run), against the line at 1: copying the last real frame for as many steps."""
    fig = Figure(figsize=LOSS_SIZE)
    ax = fig.add_subplot()
    for run, score, style in zip(runs, scores, _styles()):
        steps = np.arange(1, score["horizon"] + 1)
        ax.plot(steps, score["excess_ratio"], style, marker="o", ms=3, label=f"{run.label} ({score['windows']} windows)")
    ax.axhline(1.0, color="black", lw=1, ls=":", label="copy the last real frame")
    ax.set_xlabel(f"steps fed its own predictions, after {scores[0]['context']} real frames")
    ax.set_ylabel("held-out excess ratio at that step")
    ax.set_title("open-loop prediction: (BCE - floor) / (copy-last BCE - floor) per step")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def has_code_error(run: Run) -> bool:
    return any("code_pred_mse" in e for e in run.evals) or any("code_pred_mse" in m.get("terms", {}) for m in run.metrics)


def code_error_figure(runs: Sequence[Run]) -> Figure:
    """Code-prediction error MSE(d_t, k_t) between the predicted and the actual next input code
    over training (thesis figure 5.6): held-out evaluations as markers, the training value as
    a running average over 4096 samples."""
    fig = Figure(figsize=CODE_ERROR_SIZE)
    ax = fig.add_subplot()
    for run, style in zip(runs, _styles()):
        if not has_code_error(run):
            continue
        train = [(m["step"], m["terms"]["code_pred_mse"]) for m in run.metrics if "code_pred_mse" in m.get("terms", {})]
        color = None
        if train:
            steps, values = np.array(train).T
            (line,) = ax.plot(steps, running_mean(values, run.loss_window), style, lw=1, alpha=0.8,
                              label=f"{run.label}, train")
            color = line.get_color()
        held = [(e["step"], e["code_pred_mse"]) for e in run.evals if e.get("code_pred_mse") is not None]
        if held:
            steps, values = np.array(held).T
            ax.plot(steps, values, "o--", color=color, label=f"{run.label}, held-out")
    return _log_axes(fig, ax, "training step", "MSE(predicted code, next input code)",
                     "Code-prediction error (train: running average over 4096 samples)")


def bce_bars_figure(rows: Sequence[dict]) -> Figure:
    """Per run: next-frame BCE on training and on held-out episodes, next to the
    copy-last-frame baseline on the same frames (thesis figure 5.9). `rows` are
    `cdrl.analysis.report.evaluate_model` rows."""
    fig = Figure(figsize=bars_size(len(rows)))
    ax = fig.add_subplot()
    bars = (("train_bce", "model, train", "C0", None), ("test_bce", "model, held-out", "C1", None),
            ("train_copy_bce", "copy last frame, train", "C0", "//"), ("test_copy_bce", "copy last frame, held-out", "C1", "//"))
    x = np.arange(len(rows))
    width = 0.8 / len(bars)
    for i, (key, label, color, hatch) in enumerate(bars):
        values = [row.get(key) if row.get(key) is not None else np.nan for row in rows]
        ax.bar(x + (i - (len(bars) - 1) / 2) * width, values, width, label=label, color=color,
               hatch=hatch, alpha=0.45 if hatch else 0.9, edgecolor="black", linewidth=0.5)
    ax.set_xticks(x, [f"{row['run']}\n({row['variant']}, step {row['steps']})\nheld-out excess ratio "
                      + ("-" if row.get("test_excess_ratio") is None else f"{row['test_excess_ratio']:.3f}")
                      for row in rows])
    ax.set_ylabel("BCE per pixel")
    counts = sorted({(row["train_episodes"], row["test_episodes"]) for row in rows})
    episodes = ", ".join(f"{a} train / {b} held-out" for a, b in counts)
    ax.set_title(f"Next-frame BCE, train vs held-out\n(episodes: {episodes})")
    top = max((row[key] for row in rows for key, *_ in bars if row.get(key) is not None), default=1.0)
    ax.set_ylim(0, 1.3 * top)
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(fontsize="small", ncols=2, loc="upper center")
    fig.tight_layout()
    return fig


# ---------------------------------------------------------------- all figures


def plot_runs(run_dirs: Sequence[str | Path], out_dir: str | Path | None = None, *,
              groups: Sequence[str] | None = None, episodes: int = 2, context: int = 8,
              horizon: int = 8) -> list[Path]:
    """Write every figure for `run_dirs` into `out_dir` (default `run_dirs[0]/plots`) and return
    the paths written. `groups`: parameter groups of the norm-ratio figure; `episodes`: training
    and held-out episodes scored for the BCE bars; `context`/`horizon`: observed frames before
    the prediction and rollout figures, and rollout length.

    FileNotFoundError / ValueError (naming the path) for a directory that is not a run, a run
    with no logged step, or a run without a usable checkpoint.
    """
    if not run_dirs:
        raise ValueError("plot_runs needs at least one run directory")
    runs = [load_run(d) for d in run_dirs]
    models = []
    for run in runs:
        try:
            models.append(restore_model(run))
        except CheckpointError as exc:
            raise ValueError(f"{run.path}: {exc}") from None
    out = Path(out_dir) if out_dir is not None else RunDir(runs[0].path).plots_dir
    if out.exists() and not out.is_dir():
        raise ValueError(f"the figures' directory {out} is a file")
    out.mkdir(parents=True, exist_ok=True)

    written = [save_figure(loss_figure(runs), out / "loss.png"),
               save_figure(ratios_figure(runs, groups), out / "ratios.png")]
    if any(held_out_ratios(run)[0].size for run in runs):
        written.append(save_figure(excess_figure(runs), out / "excess.png"))
    if any(map(has_code_error, runs)):
        written.append(save_figure(code_error_figure(runs), out / "code_error.png"))
    rows, scores = [], []
    for run, model, stem in zip(runs, models, file_stems(runs)):
        train, test = run_episodes(run, episodes)
        rows.append(evaluate_model(run, model, episodes, data=(train, test)))
        longest = max(len(test[i]) for i in range(len(test)))
        if longest > context:
            scores.append(multistep_scores(model.variant, model.params, test, context,
                                           min(OPEN_LOOP_STEPS, longest - context)))
        rollout = open_loop_predictions(model, test[0], context, horizon)
        written.append(save_figure(prediction_figure(run, model, rollout), out / f"prediction_{stem}.png"))
        written.append(save_figure(rollout_figure(run, model, rollout), out / f"rollout_{stem}.png"))
    written.append(save_figure(bce_bars_figure(rows), out / "bce_bars.png"))
    if len(scores) == len(runs):
        written.append(save_figure(open_loop_figure(runs, scores), out / "open_loop.png"))
    return written


def plot_sweep(sweep_dir: str | Path) -> Path | None:
    """`curves.png` of a sweep directory: the loss curve of every configuration that logged a
    step (None when none did)."""
    sweep_dir = Path(sweep_dir)
    logged = [load_run(d) for d in sorted(sweep_dir.iterdir())
              if (d / "metrics.jsonl").is_file() and (d / "metrics.jsonl").stat().st_size > 0]
    return save_figure(loss_figure(logged), sweep_dir / "curves.png") if logged else None
