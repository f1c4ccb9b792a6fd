"""The model's predicted frames, drawn: a one-step prediction beside its input and truth, and
an open-loop rollout fed with the model's own predictions (thesis figure 5.2). Each panel is
drawn on its own data's range, which its title or row label names (a low-contrast game's frames
would otherwise be a flat grey field)."""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from matplotlib.figure import Figure

from cdrl.analysis.report import Model, Run
from cdrl.data.frames import pixel_bce
from cdrl.evaluation.multistep import open_loop

PREDICTION_SIZE = (12.0, 3.6)


def rollout_size(horizon: int) -> tuple[float, float]:
    return (1.0 + 1.5 * horizon, 3.6)


class Rollout(NamedTuple):
    """An open-loop rollout on one episode: `frames` o_0 .. o_{K+n-1}, `logits[i]` the model's
    prediction of o_{i+1} (teacher-forced for i < K, fed its own prediction after), K = `context`."""

    frames: np.ndarray  # [K + n, H, W] in [0, 1]
    logits: np.ndarray  # [K + n - 1, H, W]
    context: int

    @property
    def horizon(self) -> int:
        return self.frames.shape[0] - self.context


def _as_float(frames: np.ndarray) -> np.ndarray:
    frames = np.asarray(frames)
    return frames.astype(np.float32) / 255.0 if frames.dtype == np.uint8 else frames.astype(np.float32)


def open_loop_predictions(model: Model, episode, context: int = 8, horizon: int = 8) -> Rollout:
    """After `context` observed frames the model predicts `horizon` frames o_K .. o_{K+n-1},
    the first from the last observed frame, each later one from its own previous prediction
    (actions are the episode's). Both numbers are shortened to fit the episode."""
    n = len(episode)
    if n < 2:
        raise ValueError(f"an episode of {n} frame(s) has no next frame to predict")
    context = max(1, min(context, n - 1))
    horizon = max(1, min(horizon, n - context))
    frames = _as_float(episode.frames[: context + horizon])
    actions = np.asarray(episode.actions[: context + horizon], np.float32)
    logits = open_loop(model.variant, model.params, jnp.asarray(frames[:context, None]),
                       jnp.asarray(actions[:, None]), horizon)
    return Rollout(frames=frames, logits=np.asarray(logits[:, 0]), context=context)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def frame_range(*frames: np.ndarray) -> tuple[float, float]:
    """The grey-level range frames are drawn with: their smallest and largest value (0-1 for
    frames that are one constant), so a low-contrast game's frames use the whole grey scale."""
    lo, hi = min(float(np.min(f)) for f in frames), max(float(np.max(f)) for f in frames)
    return (lo, hi) if hi > lo else (0.0, 1.0)


def error_range(error: np.ndarray) -> tuple[float, float]:
    """The colour range of an absolute error: 0 up to its largest value (0-1 where it is 0)."""
    hi = float(np.max(error))
    return (0.0, hi) if hi > 0 else (0.0, 1.0)


def _range_label(vrange: tuple[float, float]) -> str:
    return f"[{vrange[0]:.3g}, {vrange[1]:.3g}]"


def _show(ax, image, title, vrange: tuple[float, float], cmap="gray"):
    im = ax.imshow(image, cmap=cmap, vmin=vrange[0], vmax=vrange[1], interpolation="nearest")
    ax.set_title(title, fontsize="medium")
    ax.set_xticks([])
    ax.set_yticks([])
    return im


def prediction_figure(run: Run, model: Model, rollout: Rollout) -> Figure:
    """Input frame o_t, predicted next frame õ_{t+1}, true o_{t+1} and |õ_{t+1} - o_{t+1}|, with
    t the last of the rollout's observed frames (thesis figure 5.2). Each kind of panel is
    drawn on its own data's range (`frame_range`, `error_range`; the two true frames share
    one), given in its title, and the error has a colour bar."""
    t = rollout.context - 1
    logits, truth = rollout.logits[t], rollout.frames[t + 1]
    pred = _sigmoid(logits)
    error = np.abs(pred - truth)
    bce = float(pixel_bce(jnp.asarray(logits), jnp.asarray(truth)))
    true_range, pred_range, err_range = frame_range(rollout.frames[t], truth), frame_range(pred), error_range(error)
    fig = Figure(figsize=PREDICTION_SIZE)
    axes = fig.subplots(1, 5, width_ratios=(1, 1, 1, 1, 0.05))
    _show(axes[0], rollout.frames[t], f"input $o_t$ (t = {t})\ngrey {_range_label(true_range)}", true_range)
    _show(axes[1], pred, r"predicted $\tilde{o}_{t+1}$" + f"\ngrey {_range_label(pred_range)}", pred_range)
    _show(axes[2], truth, r"true $o_{t+1}$" + f"\ngrey {_range_label(true_range)}", true_range)
    im = _show(axes[3], error, r"$|\tilde{o}_{t+1} - o_{t+1}|$" + f"\n{_range_label(err_range)}", err_range,
               cmap="magma")
    fig.colorbar(im, cax=axes[4])
    fig.suptitle(f"{run.label}, checkpoint step {model.step}: next-frame prediction on a held-out episode (BCE {bce:.4f})")
    fig.subplots_adjust(left=0.01, right=0.96, bottom=0.03, top=0.78, wspace=0.08)
    return fig


def rollout_figure(run: Run, model: Model, rollout: Rollout) -> Figure:
    """An open-loop rollout on a held-out episode: top row the true frames o_K .. o_{K+n-1},
    bottom row the predictions; the first is a one-step prediction from the last observed
    frame, every later one is made from the model's own previous prediction. Each row is
    drawn on its own data's grey range (`frame_range`), given beside it."""
    k, n = rollout.context, rollout.horizon
    truths = [rollout.frames[k + j] for j in range(n)]
    preds = [_sigmoid(rollout.logits[k - 1 + j]) for j in range(n)]
    true_range, pred_range = frame_range(*truths), frame_range(*preds)
    fig = Figure(figsize=rollout_size(n))
    axes = fig.subplots(2, n, squeeze=False)
    for j in range(n):
        _show(axes[0, j], truths[j], f"t = {k + j}", true_range)
        _show(axes[1, j], preds[j], f"+{j + 1}" if j else "1-step", pred_range)
    axes[0, 0].set_ylabel(f"truth\n{_range_label(true_range)}")
    axes[1, 0].set_ylabel(f"predicted\n{_range_label(pred_range)}")
    fig.suptitle(f"{run.label}, checkpoint step {model.step}: open-loop rollout after {k} observed frames")
    fig.subplots_adjust(left=0.75 / fig.get_figwidth(), right=0.99, bottom=0.02, top=0.8, wspace=0.05, hspace=0.3)
    return fig
