"""Every notebook in notebooks/ runs top to bottom at the `tiny` budget without a cell error,
and writes its results: the files a notebook writes at the tiny budget (under
notebooks/runs/tiny/<notebook>/) exist, are new, and hold present, finite numbers in a sane
range.

Each notebook is executed in memory (the committed .ipynb files are never written) by a fresh
kernel whose working directory is notebooks/ (Jupyter's default) and whose environment has
CDRL_NOTEBOOK_BUDGET=tiny; the notebooks then write only under notebooks/runs/tiny/ (never
notebooks/results/, which holds the full-budget results).
The kernel inherits the test session's XLA compilation cache (tests/conftest.py), so a
program that another test or notebook compiled is not compiled again.
"""
import json
import math
import time
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"
PATHS = sorted(NOTEBOOKS.glob("*.ipynb"))
# Seconds a single cell may run at the tiny budget (most of it is XLA compilation).
CELL_TIMEOUT = 600
LN2 = math.log(2)
# Slack above ln 2 (the BCE of predicting 0.5 everywhere, where the models start) for a few
# tiny steps, and on the entropy floor (the same frames, float32 sums).
SLACK, EPS = 0.01, 1e-5


def test_there_are_notebooks():
    assert [p.name for p in PATHS][:3] == ["01_quickstart.ipynb", "02_variants.ipynb", "03_controller.ipynb"]


def _finite(x, what):
    assert isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x), f"{what}: {x!r}"
    return x


def _jsonl(path):
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _check_bce(bce, copy_bce, entropy, what):
    """A held-out evaluation: the targets' entropy is a floor under any BCE on them; the model
    starts at ln 2 and a few tiny steps do not take it much above."""
    _finite(entropy, f"{what} entropy")
    assert 0 < entropy < LN2, (what, entropy)
    assert entropy - EPS <= _finite(bce, f"{what} bce") <= LN2 + SLACK, (what, bce, entropy)
    assert entropy - EPS <= _finite(copy_bce, f"{what} copy_bce"), (what, copy_bce, entropy)


def _check_figures(runs, names, since):
    for name in names:
        path = runs / "figures" / name
        assert path.is_file() and path.stat().st_size > 1000 and path.stat().st_mtime >= since, path
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", path


def _check_quickstart(runs, since):
    """A main run trained in two halves (resumed) and straight through: identical losses,
    held-out evaluations after each half, and the figures."""
    records = {}
    for name in ("main", "main-straight"):
        run = runs / name
        assert json.loads((run / "config.json").read_text())["steps"] == 6
        records[name] = _jsonl(run / "metrics.jsonl")
        assert [r["step"] for r in records[name]] == list(range(6)), name
        for r in records[name]:
            assert 0 < _finite(r["loss"], f"{name} loss") <= LN2 + SLACK, (name, r["loss"])
        evals = _jsonl(run / "eval.jsonl")
        assert evals[-1]["step"] == 6 and (run / "eval.jsonl").stat().st_mtime >= since
        for e in evals:
            _check_bce(e["bce"], e["copy_bce"], e["target_entropy"], f"{name} step {e['step']}")
    assert [r["step"] for r in _jsonl(runs / "main" / "eval.jsonl")] == [3, 6]
    assert [r["loss"] for r in records["main"]] == [r["loss"] for r in records["main-straight"]]
    _check_figures(runs, ["observation.png", "episode.png", "loss.png", "prediction.png", "rollout.png"], since)


OFFLINE = ["baseline_ff", "baseline_recurrent", "main", "main_action", "residual", "residual_error",
           "closed_loop_plus", "closed_loop_minus"]
CODE_PRED = {"baseline_recurrent", "residual", "residual_error"}  # the variants with a code-prediction error


def _check_variants(runs, since):
    """variants.json: every offline variant, both seeds, 4 steps, no divergence; BCEs between
    the entropy floor and ln 2; the summary is the mean of the seeds."""
    path = runs / "variants.json"
    assert path.stat().st_mtime >= since
    results = json.loads(path.read_text())
    assert results["budget"] == "tiny" and results["seeds"] == [0, 1]
    assert sorted(results["variants"]) == sorted(OFFLINE)
    for variant, entry in results["variants"].items():
        rows = entry["per_seed"]
        assert [r["seed"] for r in rows] == [0, 1], variant
        for r in rows:
            what = f"{variant} seed {r['seed']}"
            assert r["steps"] == 4 and r["diverged_at"] is None, what
            _check_bce(r["test_bce"], r["test_copy_bce"], r["test_target_entropy"], f"{what} test")
            _check_bce(r["train_bce"], r["train_copy_bce"], r["train_target_entropy"], f"{what} train")
            assert 0 < _finite(r["final_train_loss"], f"{what} final_train_loss") < 1, what
            if variant in CODE_PRED:
                assert _finite(r["test_code_pred_mse"], f"{what} code_pred_mse") >= 0, what
            else:
                assert r["test_code_pred_mse"] is None, what
            assert (NOTEBOOKS.parent / r["path"] / "metrics.jsonl").is_file(), what
        for key in ("test_bce", "train_bce", "test_target_entropy", "final_train_loss"):
            mean = sum(r[key] for r in rows) / len(rows)
            assert entry["summary"][key]["mean"] == pytest.approx(mean, rel=1e-9), (variant, key)
    assert sorted(results["code_scales"]) == [f"{v}/seed{s}" for v in ("residual", "residual_error") for s in (0, 1)]
    for name, scales in results["code_scales"].items():
        assert all(_finite(x, name) >= 0 for x in scales.values()), (name, scales)
        assert scales["code_variance"] > 0, name
    _check_figures(runs, ["fig5_1_loss.png", "fig5_2_prediction_baseline_ff.png", "fig5_2_prediction_main.png",
                          "fig5_3_loss.png", "fig5_4_5_ratios.png", "fig5_4_5_ratios_first10pct.png",
                          "fig5_6_code_error.png", "fig5_7_loss.png", "fig5_8_loss.png", "fig5_9_bce_bars.png",
                          "fig5_9_excess.png"], since)


def _check_return(table, what, max_steps=12):
    """A policy's returns over the 2 held-out games of at most 12 steps: finite, at most 5 (a
    few pellets' worth of length) per step either way, inside their confidence interval."""
    length = _finite(table["mean_length"], f"{what} mean_length")
    assert table["episodes"] == 2 and 1 <= length <= max_steps, (what, table)
    ret = _finite(table["mean_return"], f"{what} mean_return")
    assert abs(ret) <= 5.0 * length, (what, table)
    lo, hi = (_finite(x, f"{what} ci95") for x in table["ci95"])
    assert lo - EPS <= ret <= hi + EPS, (what, table)


def _check_controller(runs, since):
    """controller.json: the four online runs of seed 0 and the two baseline policies."""
    path = runs / "controller.json"
    assert path.stat().st_mtime >= since
    results = json.loads(path.read_text())
    assert results["budget"] == "tiny" and results["seeds"] == [0]
    names = ["final_proposal-controller", "final_proposal-all", "reward_prediction-controller", "action_loop"]
    assert list(results["runs"]) == names
    for name in names:
        r = results["runs"][name]["per_seed"]["0"]
        assert r["steps_logged"] == 4 and r["diverged"] is None, (name, r)
        _check_return(r["controller"], f"{name} controller")
        assert abs(_finite(r["real_reward_per_step"], f"{name} reward")) <= 5.0, (name, r)
        assert abs(_finite(r["predicted_reward_per_step"], f"{name} predicted reward")) < 10, (name, r)
        if name == "action_loop":
            assert r["predicted_reward_per_step"] == 0.0  # it predicts no reward
        assert 0 < _finite(r["final_obs_bce"], f"{name} obs_bce") <= LN2 + SLACK, (name, r)
        assert len(r["action_mean"]) == 3 and all(0 <= _finite(a, name) <= 1 for a in r["action_mean"]), (name, r)
        assert len(_jsonl(runs / name / "seed0" / "metrics.jsonl")) == 4, name
    for policy in ("uniform", "behaviour"):
        _check_return(results["baselines"][policy], policy)
    _check_figures(runs, ["training.png"], since)


CHECKS = {"01_quickstart": _check_quickstart, "02_variants": _check_variants, "03_controller": _check_controller}


@pytest.mark.parametrize("path", PATHS, ids=[p.stem for p in PATHS])
def test_notebook_runs_at_tiny_budget(path, monkeypatch):
    monkeypatch.setenv("CDRL_NOTEBOOK_BUDGET", "tiny")  # the kernel inherits this process's environment
    before = path.read_bytes()
    full_results = {p.name: p.read_bytes() for p in (NOTEBOOKS / "results").glob("*")}
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=CELL_TIMEOUT, kernel_name="python3",
                                     resources={"metadata": {"path": str(NOTEBOOKS)}})
    since = time.time() - 1  # file times have a coarser clock on some file systems
    client.execute()  # raises CellExecutionError, naming the cell, on the first error
    assert path.read_bytes() == before
    errors = [out for cell in nb.cells if cell.cell_type == "code" for out in cell.get("outputs", [])
              if out.get("output_type") == "error"]
    assert not errors  # (a cell tagged raises-exception may error without execute() raising)
    assert {p.name: p.read_bytes() for p in (NOTEBOOKS / "results").glob("*")} == full_results
    assert path.stem in CHECKS, f"no check of what {path.name} writes"
    CHECKS[path.stem](NOTEBOOKS / "runs" / "tiny" / path.stem, since)
