"""TensorBoard event files of a run, in RUN_DIR/tb, written with tensorboardX (no TensorFlow).

Every number of a `metrics.jsonl` record becomes a scalar at its step: `loss`, `terms/<term>`,
`max_ratio`, `ratio/<parameter group>` (||grad|| / ||param||), `fps`, and for online runs the
reward, returns and noise; every number of an `eval.jsonl` record becomes `eval/<name>`
(held-out `bce`, `copy_bce`, `target_entropy`, `excess_ratio`, `code_pred_mse`; the policy
comparison of controller runs). At each held-out evaluation of an offline run, the image
`predictions` shows the first frames of a held-out episode to predict (top row) above the
model's predictions of them (bottom row). A resumed run purges the events at and after the
step it resumes from, so TensorBoard shows each step once. View with
`tensorboard --logdir runs` (tensorboard is a separate, optional install).
"""
from __future__ import annotations

import functools
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from cdrl.data.episode import Episode
from cdrl.data.frames import as_float
from cdrl.models.base import StepInput, Variant

PREDICTED_FRAMES = 8


def scalars(record: dict, prefix: str = "") -> dict[str, float]:
    """The numbers of a log record as TensorBoard tags -> values (nested dicts and lists
    flattened with '/'; the step, strings and missing values left out)."""
    out: dict[str, float] = {}
    for key, value in record.items():
        if prefix == "" and key == "step":
            continue
        tag = f"{prefix}{'ratio' if key == 'ratios' and not prefix else key}"
        if isinstance(value, dict):
            out.update(scalars(value, tag + "/"))
        elif isinstance(value, (list, tuple)):
            out.update(scalars({str(i): v for i, v in enumerate(value)}, tag + "/"))
        elif isinstance(value, (bool, int, float)):
            out[tag] = float(value)
    return out


@functools.partial(jax.jit, static_argnums=0)
def _predict(variant: Variant, params, xs: StepInput) -> jax.Array:
    _, outs = variant.unroll(params, variant.init_carry(1), xs)
    return jax.nn.sigmoid(outs["logits"])


def prediction_image(variant: Variant, params, episode: Episode, frames: int = PREDICTED_FRAMES) -> np.ndarray:
    """[2 H, n W] in [0, 1]: the frames o_1 .. o_n of `episode` (top) and the model's
    one-step predictions of them from o_0 .. o_{n-1} (bottom), n = min(frames, len - 1)."""
    n = max(1, min(frames, len(episode) - 1))
    xs = StepInput(obs=as_float(jnp.asarray(episode.frames[:n]))[:, None],
                   action=jnp.asarray(episode.actions[:n], jnp.float32)[:, None],
                   is_first=jnp.arange(n)[:, None] == 0)
    predicted = np.asarray(_predict(variant, params, xs))[:, 0]
    target = np.asarray(as_float(jnp.asarray(episode.frames[1:n + 1])))

    def row(images):
        return np.concatenate(list(images), axis=1)

    return np.clip(np.concatenate([row(target), row(predicted)], axis=0), 0.0, 1.0)


class TBLog:
    """A run's TensorBoard writer, or a no-op when `enabled` is false. `start`: the step the
    run (re)starts from; events of earlier processes at and after it are purged."""

    def __init__(self, directory: str | Path, start: int = 0, enabled: bool = True):
        self.writer = None
        if enabled:
            from tensorboardX import SummaryWriter

            # The suffix keeps two writers of one second and host (a run and its quick resume)
            # from sharing, and so overwriting, one event file.
            self.writer = SummaryWriter(logdir=str(directory), purge_step=start if start > 0 else None,
                                        flush_secs=30, filename_suffix=f".{os.getpid()}.from{start}")

    def _scalars(self, step: int, values: dict[str, float]) -> None:
        for tag, value in values.items():
            self.writer.add_scalar(tag, value, step)

    def step(self, record: dict) -> None:
        """One `metrics.jsonl` record."""
        if self.writer is not None:
            self._scalars(int(record["step"]), scalars(record))

    def eval(self, record: dict) -> None:
        """One `eval.jsonl` record."""
        if self.writer is not None:
            self._scalars(int(record["step"]), scalars(record, "eval/"))

    def replay_evals(self, records: list[dict], start: int) -> list[dict]:
        """Write again the kept evaluations at step `start` that the purge of a resumed run
        removed (an evaluation at step s follows training step s - 1); returns them."""
        kept = [r for r in records if r["step"] == start] if start > 0 else []
        for record in kept:
            self.eval(record)
        return kept

    def image(self, step: int, image: np.ndarray) -> None:
        """The image `predictions` at `step` (a `prediction_image`)."""
        if self.writer is not None:
            self.writer.add_image("predictions", image, step, dataformats="HW")

    def flush(self) -> None:
        if self.writer is not None:
            self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None
