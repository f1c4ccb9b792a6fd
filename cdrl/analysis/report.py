"""Reading finished (or interrupted) runs back: their logs, their latest good model, and a
train-vs-test evaluation table (the numbers behind thesis figure 5.9).

`load_run(dir)` reads a run directory's config and logs; `restore_model(run)` restores the
newest checkpoint that loads cleanly; `evaluate_model` scores it on held-out and on training
episodes; `eval_runs(dirs)` does all three for several runs and prints a table.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from cdrl.evaluation.metrics import check_episodes, evaluate, prefixed
from cdrl.evaluation.multistep import multistep_scores
from cdrl.models import make_variant
from cdrl.models.base import Variant
from cdrl.runs.config import RunConfig
from cdrl.runs.rundir import RunDir
from cdrl.runs.sources import load_episodes
from cdrl.runs.init_from import restore_params

# The thesis reports the training loss as a running average over the previous 4096 samples.
LOSS_WINDOW_SAMPLES = 4096


@dataclasses.dataclass(frozen=True)
class Run:
    """A run directory's config and logs (`metrics` sorted by step, one record per step)."""

    path: Path
    config: RunConfig
    metrics: list[dict]
    evals: list[dict]

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def label(self) -> str:
        return f"{self.path.name} ({self.config.variant})"

    @property
    def samples_per_step(self) -> int:
        return self.config.batch * self.config.unroll

    @property
    def loss_window(self) -> int:
        """Steps in the running average of the training loss: 4096 samples' worth."""
        return max(1, LOSS_WINDOW_SAMPLES // self.samples_per_step)


@dataclasses.dataclass(frozen=True)
class Model:
    """A run's variant and the parameters of its latest good checkpoint."""

    variant: Variant
    params: Any
    step: int


def _by_step(records: list[dict]) -> list[dict]:
    """One record per step (the last one written wins), in step order."""
    return [r for _, r in sorted({int(r["step"]): r for r in records}.items())]


def load_run(run_dir: str | Path) -> Run:
    """Read a run directory. FileNotFoundError if it or its metrics file is missing,
    ValueError if it is not a run directory or its metrics file holds no step."""
    run = RunDir(run_dir)
    config = run.read_config()
    if not run.metrics.path.is_file():
        raise FileNotFoundError(f"{run.metrics.path} does not exist: the run has not logged a training step yet")
    metrics = _by_step(run.metrics.read())
    if not metrics:
        raise ValueError(f"{run.metrics.path} is empty: the run has not logged a training step yet")
    return Run(path=run.path, config=config, metrics=metrics, evals=_by_step(run.evals.read()))


def restore_model(run: Run) -> Model:
    """The run's latest good checkpoint. FileNotFoundError if it has none;
    `cdrl.runs.checkpoint.CheckpointError` (a RuntimeError) if every one is corrupt."""
    cfg, params, step = restore_params(RunDir(run.path))
    return Model(variant=make_variant(cfg.variant, cfg.arch), params=params, step=step)


def run_episodes(run: Run, n: int) -> tuple[list, list]:
    """The first `n` training and the first `n` held-out episodes of the run's data."""
    train, test = load_episodes(run.config, RunDir(run.path).data_cache)
    return [train[i] for i in range(min(n, len(train)))], [test[i] for i in range(min(n, len(test)))]


def running_mean(values: Sequence[float], window: int) -> np.ndarray:
    """Mean of each value and the up to `window - 1` values before it."""
    x = np.asarray(values, np.float64)
    csum = np.concatenate([[0.0], np.cumsum(x)])
    idx = np.arange(1, x.size + 1)
    lo = np.maximum(idx - window, 0)
    return (csum[idx] - csum[lo]) / (idx - lo)


def training_loss(run: Run) -> tuple[np.ndarray, np.ndarray]:
    """(steps, per-step training next-frame BCE): the `obs_bce` term where logged, which is the
    optimised loss for every single-stage variant and the comparable number for the staged
    `baseline_recurrent`; else the total loss."""
    steps = np.array([m["step"] for m in run.metrics])
    loss = np.array([m.get("terms", {}).get("obs_bce", m["loss"]) for m in run.metrics], np.float64)
    return steps, loss


def evaluate_model(run: Run, model: Model, episodes: int, data: tuple[list, list] | None = None) -> dict:
    """One table row: BCE, copy-last-frame BCE, entropy floor, excess ratio (and code-prediction
    MSE where the variant has one) on `episodes` training and `episodes` held-out episodes (`data`, default
    `run_episodes(run, episodes)`), plus the final training loss (running average over the
    last 4096 samples). Missing numbers are None."""
    check_episodes(episodes)
    train, test = data if data is not None else run_episodes(run, episodes)
    row: dict[str, Any] = {"run": run.name, "path": str(run.path), "variant": run.config.variant, "steps": model.step}
    for split, eps in (("train", train), ("test", test)):
        if not eps:
            raise ValueError(f"{run.path}: the run's data has no {split} episodes")
        row[f"{split}_episodes"] = len(eps)
        row.update(prefixed(evaluate(model.variant, model.params, eps, run.config.unroll), split))
    _, loss = training_loss(run)
    row["final_train_loss"] = float(running_mean(loss, run.loss_window)[-1])
    return row


COLUMNS = (
    ("run", "run"), ("variant", "variant"), ("steps", "steps"),
    ("train_bce", "train BCE"), ("test_bce", "test BCE"),
    ("test_copy_bce", "copy-last BCE"), ("test_target_entropy", "entropy floor"),
    ("test_excess_ratio", "excess ratio"),
    ("test_code_pred_mse", "code-pred MSE"),
    ("final_train_loss", "final train loss"),
)


def format_table(rows: list[dict]) -> str:
    """The rows as an aligned text table (BCEs on the held-out episodes unless marked train;
    the copy-last-frame baseline, the floor, the excess ratio (BCE - floor) / (copy-last BCE -
    floor) and code-prediction MSE are on the held-out episodes)."""
    def cell(value):
        if value is None:
            return "-"
        if isinstance(value, float):
            return f"{value:.4f}" if abs(value) >= 1e-3 else f"{value:.3e}"
        return str(value)

    table = [[title for _, title in COLUMNS]] + [[cell(row.get(key)) for key, _ in COLUMNS] for row in rows]
    widths = [max(len(line[i]) for line in table) for i in range(len(COLUMNS))]
    lines = ["  ".join(c.ljust(w) if i < 2 else c.rjust(w) for i, (c, w) in enumerate(zip(line, widths)))
             for line in table]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def format_open_loop(rows: Sequence[dict]) -> str:
    """The open-loop table: per run the held-out excess ratio at steps 1, 5, 10, 15, ... K."""
    horizon = rows[0]["open_loop"]["horizon"]
    steps = sorted({1, horizon} | set(range(5, horizon, 5)))
    lines = [f"open loop after {rows[0]['open_loop']['context']} real frames: held-out excess ratio at step k "
             "(the model fed its own predictions; 1 = copying the last real frame for k steps)",
             f"{'run':32s} {'windows':>8s} " + " ".join(f"{'k=' + str(k):>7s}" for k in steps)]
    for row in rows:
        scores = row["open_loop"]
        lines.append(f"{row['run'][-32:]:32s} {scores['windows']:8d} "
                     + " ".join(f"{scores['excess_ratio'][k - 1]:7.3f}" for k in steps))
    return "\n".join(lines)


def eval_runs(run_dirs: Sequence[str | Path], episodes: int | None = None, horizon: int | None = None,
              context: int = 8) -> list[dict]:
    """Evaluate each run's latest good checkpoint on its held-out episodes (default: the run's
    `eval_episodes`) and on as many training episodes; print a table; return the rows. With
    `horizon`, also the open-loop scores on the same held-out episodes
    (`cdrl.evaluation.multistep`: `context` real frames, then `horizon` steps fed its own
    predictions) in each row's `open_loop`, and their table."""
    check_episodes(episodes)
    for name, value in (("horizon", horizon), ("context", context)):
        if value is not None and value < 1:
            raise ValueError(f"{name} must be >= 1, got {value}")
    runs = [load_run(d) for d in run_dirs]
    rows = []
    for run in runs:
        n = episodes if episodes is not None else run.config.eval_episodes
        model, data = restore_model(run), run_episodes(run, n)
        row = evaluate_model(run, model, n, data)
        if horizon is not None:
            row["open_loop"] = multistep_scores(model.variant, model.params, data[1], context, horizon)
        rows.append(row)
    print(format_table(rows))
    if horizon is not None:
        print(format_open_loop(rows))
    return rows
