"""The figures and the evaluation table of finished runs: `cdrl.analysis.plots`, `cdrl.analysis.report`."""
import json
import math
import shutil
from types import SimpleNamespace

import matplotlib.image
import numpy as np
import pytest

from cdrl.cli import main as cli_main
from cdrl.analysis.plots import (DPI, Rollout, frame_range, plot_runs, prediction_figure, resolve_groups,
                                 rollout_figure)
from cdrl.analysis.report import eval_runs, running_mean
from cdrl.runs.config import RunConfig
from cdrl.runs.train import train_run

RUN = dict(data="synthetic", preset="tiny", episodes=6, episode_steps=30, unroll=8, batch=2, lr=0.3,
           steps=30, checkpoint_every=15, eval_every=15, eval_episodes=1)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    train_run(RunConfig(variant="main", **RUN), root / "a", progress=False)
    train_run(RunConfig(variant="residual", seed=1, **RUN), root / "b", progress=False)
    return [root / "a", root / "b"]


def _pixels(inches):
    """(height, width) in pixels of a figure of (width, height) inches."""
    return round(inches[1] * DPI), round(inches[0] * DPI)


def test_plot_runs_writes_every_figure_at_its_size(runs):
    written = plot_runs(runs)
    out = runs[0] / "plots"
    # Sizes in inches: loss/code error 8x5; ratios 5 per group x 4.5 (two groups on the tiny
    # preset); prediction 12x3.6; rollout 1 + 1.5 per frame (8) x 3.6; bars max(6, 2 + 1.8 per run) x 5;
    # the open-loop scores 8x5.
    expected = {
        "loss.png": (8, 5), "excess.png": (8, 5), "ratios.png": (10, 4.5), "code_error.png": (8, 5),
        "open_loop.png": (8, 5),
        "prediction_a.png": (12, 3.6), "prediction_b.png": (12, 3.6),
        "rollout_a.png": (13, 3.6), "rollout_b.png": (13, 3.6), "bce_bars.png": (6, 5),
    }
    assert sorted(p.name for p in written) == sorted(expected)
    assert all(p.parent == out for p in written)
    assert sorted(p.name for p in out.iterdir()) == sorted(expected), "temporary files left behind"
    for path in written:
        image = matplotlib.image.imread(path)
        assert image.shape[:2] == _pixels(expected[path.name]), path.name
        assert image.std() > 0.01, f"{path.name} is blank"


def test_eval_runs_prints_a_table_and_returns_finite_rows(runs, capsys):
    rows = eval_runs(runs)
    table = capsys.readouterr().out
    assert "train BCE" in table and "test BCE" in table
    assert [row["run"] for row in rows] == ["a", "b"]
    assert [row["variant"] for row in rows] == ["main", "residual"]
    # One table line per run, after the header and its rule, with the run's numbers.
    lines = table.strip().splitlines()
    assert len(lines) == 4 and set(lines[1]) <= {"-", " "}
    for line, row in zip(lines[2:], rows):
        assert line.split()[:3] == [row["run"], row["variant"], "30"]
        assert f"{row['train_bce']:.4f}" in line and f"{row['test_bce']:.4f}" in line
    for run, row in zip(runs, rows):
        assert row["steps"] == 30 and row["train_episodes"] == row["test_episodes"] == 1
        for key in ("train_bce", "test_bce", "train_copy_bce", "test_copy_bce", "final_train_loss"):
            assert math.isfinite(row[key]) and row[key] > 0, key
        assert row["test_bce"] >= row["test_target_entropy"] - 1e-6  # the floor of any BCE on those frames
        # The final checkpoint on the same held-out episode as the run's own last evaluation.
        logged = json.loads((run / "eval.jsonl").read_text().splitlines()[-1])
        assert logged["step"] == 30 and row["test_bce"] == pytest.approx(logged["bce"], rel=1e-5)
        json.dumps(row, allow_nan=False)
    assert rows[0]["test_code_pred_mse"] is None
    assert math.isfinite(rows[1]["test_code_pred_mse"])


def test_not_a_run_is_a_clear_error(tmp_path, runs, capsys):
    with pytest.raises(ValueError, match=f"{tmp_path}.*not a run directory"):
        plot_runs([tmp_path])
    with pytest.raises(FileNotFoundError, match="missing"):
        plot_runs([tmp_path / "missing"])
    empty = tmp_path / "empty"
    empty.mkdir()
    shutil.copy(runs[0] / "config.json", empty / "config.json")
    (empty / "metrics.jsonl").write_text("")
    with pytest.raises(ValueError, match="metrics.jsonl is empty"):
        eval_runs([empty])
    assert cli_main(["plot", str(tmp_path)]) == 2
    assert "not a run directory" in capsys.readouterr().err


def test_ratio_groups_fall_back_to_the_deepest_layer_of_a_smaller_preset():
    tiny = {"obs_enc/conv0/kernel", "obs_enc/conv2/kernel", "obs_dec/deconv2/kernel", "lstm/w_input"}
    assert resolve_groups(None, tiny) == ["obs_enc/conv2/kernel", "obs_dec/deconv2/kernel"]
    assert resolve_groups(["lstm/w_input"], tiny) == ["lstm/w_input"]
    with pytest.raises(ValueError, match="lstm/w_recurrent"):
        resolve_groups(["lstm/w_recurrent"], tiny)


def test_running_mean_averages_the_trailing_window():
    np.testing.assert_allclose(running_mean([1, 2, 3, 4, 5], 2), [1, 1.5, 2.5, 3.5, 4.5])
    np.testing.assert_allclose(running_mean([1, 2, 3], 100), [1, 1.5, 2])


def test_frames_are_drawn_on_their_own_range_named_on_the_figure():
    """A low-contrast game's frames (a recorded Atari frame lies in [0.5, 0.85]) use the whole
    grey scale: the true frames, the predictions and the error each on their data's range,
    which the panel's title (the rollout's row label) gives; frames spanning 0-1 keep 0-1."""
    rng = np.random.default_rng(0)
    frames = rng.uniform(0.5, 0.85, (6, 16, 16)).astype(np.float32)
    frames[:, 0, :2] = [0.5, 0.85]
    pred = np.full((5, 16, 16), 0.6)
    pred[:, 0, :2] = [0.55, 0.7]
    rollout = Rollout(frames=frames, logits=np.log(pred) - np.log1p(-pred), context=3)
    run, model = SimpleNamespace(label="low contrast"), SimpleNamespace(step=7)

    fig = prediction_figure(run, model, rollout)
    input_ax, pred_ax, true_ax, error_ax = fig.axes[:4]
    assert input_ax.images[0].get_clim() == pytest.approx((0.5, 0.85))
    assert true_ax.images[0].get_clim() == pytest.approx((0.5, 0.85))
    assert pred_ax.images[0].get_clim() == pytest.approx((0.55, 0.7))
    assert error_ax.images[0].get_clim() == pytest.approx((0.0, np.abs(pred[2] - frames[3]).max()))
    assert "[0.5, 0.85]" in true_ax.get_title() and "[0.55, 0.7]" in pred_ax.get_title()

    fig = rollout_figure(run, model, rollout)
    truth_row, pred_row = fig.axes[:3], fig.axes[3:6]
    assert all(ax.images[0].get_clim() == pytest.approx((0.5, 0.85)) for ax in truth_row)
    assert all(ax.images[0].get_clim() == pytest.approx((0.55, 0.7)) for ax in pred_row)
    assert "[0.5, 0.85]" in truth_row[0].get_ylabel() and "[0.55, 0.7]" in pred_row[0].get_ylabel()

    full = np.linspace(0, 1, 16 * 16).reshape(16, 16)
    assert frame_range(full) == (0.0, 1.0) and frame_range(np.full((4, 4), 0.7)) == (0.0, 1.0)

