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

import jax
import numpy as np

from cdrl.evaluation.metrics import check_episodes, evaluate, prefixed
from cdrl.models import make_variant
from cdrl.models.base import Variant
from cdrl.runs.config import RunConfig
from cdrl.runs.rundir import RunDir
from cdrl.runs.sources import load_episodes
from cdrl.training.step import init_state

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
    cfg = run.config
    directory = RunDir(run.path).checkpoint_dir
    if not directory.is_dir() or not any(p.name.isdigit() for p in directory.iterdir()):
        raise FileNotFoundError(f"{directory} holds no checkpoint")
    variant = make_variant(cfg.variant, cfg.arch)
    hp = cfg.hparams(variant)
    # The abstract shape of a state is all a restore needs; tracing it is much cheaper than
    # initialising one eagerly.
    like = jax.eval_shape(lambda: init_state(variant, jax.random.PRNGKey(0), cfg.batch, hp))
    state, meta = RunDir(run.path).read_checkpoints().restore_newest(like)
    return Model(variant=variant, params=state.params, step=int(meta["step"]))


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


def eval_runs(run_dirs: Sequence[str | Path], episodes: int | None = None) -> list[dict]:
    """Evaluate each run's latest good checkpoint on its held-out episodes (default: the run's
    `eval_episodes`) and on as many training episodes; print a table; return the rows."""
    check_episodes(episodes)
    runs = [load_run(d) for d in run_dirs]
    rows = []
    for run in runs:
        n = episodes if episodes is not None else run.config.eval_episodes
        rows.append(evaluate_model(run, restore_model(run), n))
    print(format_table(rows))
    return rows
