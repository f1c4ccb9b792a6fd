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
from cdrl.runs.config import upgrade
import math
import re
import statistics
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.e2e

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


def _check_bce(bce, copy_bce, entropy, what, ratio=None):
    """A held-out evaluation: the targets' entropy is a floor under any BCE on them; the model
    starts at ln 2 and a few tiny steps do not take it much above. The excess ratio, where
    given, is (BCE - floor) / (copy-last BCE - floor) of these numbers, finite and > 0."""
    _finite(entropy, f"{what} entropy")
    assert 0 < entropy < LN2, (what, entropy)
    assert entropy - EPS <= _finite(bce, f"{what} bce") <= LN2 + SLACK, (what, bce, entropy)
    assert entropy + EPS < _finite(copy_bce, f"{what} copy_bce"), (what, copy_bce, entropy)
    if ratio is not None:
        assert _finite(ratio, f"{what} excess ratio") > 0, (what, ratio)
        assert ratio == pytest.approx((bce - entropy) / (copy_bce - entropy), rel=1e-6), (what, ratio, bce, copy_bce, entropy)


def _check_figures(runs, names, since):
    for name in names:
        path = runs / "figures" / name
        assert path.is_file() and path.stat().st_size > 1000 and path.stat().st_mtime >= since, path
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", path


def _check_recipe(config, what):
    """A config.json of the default recipe: its resolved values, and the encoder's input
    standardised by statistics measured from the data."""
    assert config["recipe"] == "tuned", what
    assert (config["optimizer"], config["lr"], config["momentum"], config["obs_norm"]) == ("sgd", 2.0, 0.9, "data"), what
    assert (config["batch"], config["unroll"], config["fc_init_gain"]) == (4, 8, 5.0), what
    assert 0 < _finite(config["obs_mean"], what) < 1 and 0 < _finite(config["obs_std"], what) < 1, what


def _check_quickstart(runs, since):
    """A main run of the default recipe trained in two halves (resumed) and straight through:
    identical losses and held-out evaluations (every 3 steps, with their excess ratios), and
    the figures."""
    records, evals = {}, {}
    for name in ("main", "main-straight"):
        run = runs / name
        config = upgrade(json.loads((run / "config.json").read_text()))
        assert (config["steps"], config["eval_every"]) == (6, 3), name
        _check_recipe(config, name)
        records[name] = _jsonl(run / "metrics.jsonl")
        assert [r["step"] for r in records[name]] == list(range(6)), name
        for r in records[name]:
            assert 0 < _finite(r["loss"], f"{name} loss") <= LN2 + SLACK, (name, r["loss"])
        evals[name] = _jsonl(run / "eval.jsonl")
        assert [e["step"] for e in evals[name]] == [3, 6], name
        assert (run / "eval.jsonl").stat().st_mtime >= since
        for e in evals[name]:
            _check_bce(e["bce"], e["copy_bce"], e["target_entropy"], f"{name} step {e['step']}", e["excess_ratio"])
    assert [r["loss"] for r in records["main"]] == [r["loss"] for r in records["main-straight"]]
    assert evals["main"] == evals["main-straight"]
    _check_figures(runs, ["observation.png", "episode.png", "loss.png", "excess.png", "prediction.png", "rollout.png"],
                   since)


OFFLINE = ["baseline_ff", "baseline_recurrent", "main", "main_action", "residual", "residual_error",
           "closed_loop_plus", "closed_loop_minus"]
CODE_PRED = {"baseline_recurrent", "residual", "residual_error"}  # the variants with a code-prediction error


def _check_variants(runs, since):
    """variants.json: every offline variant, both seeds, 4 steps of the default recipe, no
    divergence; BCEs between the entropy floor and ln 2 and their excess ratios; the summary
    is the mean, std, min and max of the seeds; the held-out excess-ratio curve of every seed
    (evaluations every 2 steps) matches its eval.jsonl; a line of numbers per thesis claim."""
    path = runs / "variants.json"
    assert path.stat().st_mtime >= since
    results = json.loads(path.read_text())
    assert results["budget"] == "tiny" and results["seeds"] == [0, 1]
    assert sorted(results["variants"]) == sorted(OFFLINE)
    for variant, entry in results["variants"].items():
        rows = entry["per_seed"]
        assert [r["seed"] for r in rows] == [0, 1], variant
        assert "--recipe tuned" in entry["command"] and "--seed 0 1" in entry["command"], entry["command"]
        for r in rows:
            what = f"{variant} seed {r['seed']}"
            assert r["steps"] == 4 and r["diverged_at"] is None, what
            _check_bce(r["test_bce"], r["test_copy_bce"], r["test_target_entropy"], f"{what} test", r["test_excess_ratio"])
            _check_bce(r["train_bce"], r["train_copy_bce"], r["train_target_entropy"], f"{what} train",
                       r["train_excess_ratio"])
            assert 0 < _finite(r["final_train_loss"], f"{what} final_train_loss") < 1, what
            if variant in CODE_PRED:
                assert _finite(r["test_code_pred_mse"], f"{what} code_pred_mse") >= 0, what
            else:
                assert r["test_code_pred_mse"] is None, what
            run = NOTEBOOKS.parent / r["path"]
            assert (run / "metrics.jsonl").is_file(), what
            _check_recipe(upgrade(json.loads((run / "config.json").read_text())), what)
            evals = _jsonl(run / "eval.jsonl")
            assert [e["step"] for e in evals] == [2, 4], what
            for e in evals:
                _check_bce(e["bce"], e["copy_bce"], e["target_entropy"], f"{what} step {e['step']}", e["excess_ratio"])
            assert evals[-1]["excess_ratio"] == pytest.approx(r["test_excess_ratio"], rel=1e-6), what
        for key in ("test_bce", "train_bce", "test_target_entropy", "final_train_loss", "test_excess_ratio",
                    "train_excess_ratio"):
            seeds = [r[key] for r in rows]
            summary = entry["summary"][key]
            assert summary["mean"] == pytest.approx(sum(seeds) / len(seeds), rel=1e-9), (variant, key)
            assert (summary["min"], summary["max"]) == (min(seeds), max(seeds)), (variant, key)
            assert summary["std"] == pytest.approx(statistics.stdev(seeds), rel=1e-6, abs=1e-12), (variant, key)
        curve = entry["held_out_excess_curve"]
        assert curve["frames"] == [2 * 32, 4 * 32], variant  # 4 streams x 8 frames a step
        for r, ratios in zip(rows, curve["per_seed"]):
            evals = _jsonl(NOTEBOOKS.parent / r["path"] / "eval.jsonl")
            assert ratios == pytest.approx([e["excess_ratio"] for e in evals], rel=1e-9), variant
    claims = results["claims"]
    assert [c["figure"] for c in claims] == ["5.1", "5.1", "5.3", "5.6", "5.7", "5.7", "5.8", "5.9"]
    for c in claims:
        assert c["claim"] and re.search(r"\d\.\d{3}", c["numbers"]), c  # numbers, not blanks
        assert "nan" not in c["numbers"].lower(), c
    assert sorted(results["code_scales"]) == [f"{v}/seed{s}" for v in ("residual", "residual_error") for s in (0, 1)]
    for name, scales in results["code_scales"].items():
        assert all(_finite(x, name) >= 0 for x in scales.values()), (name, scales)
        assert scales["code_variance"] > 0, name
    _check_figures(runs, ["fig5_1_loss.png", "fig5_1_excess.png", "fig5_2_prediction_baseline_ff.png",
                          "fig5_2_prediction_main.png", "fig5_3_loss.png", "fig5_3_excess.png", "fig5_4_5_ratios.png",
                          "fig5_4_5_ratios_first10pct.png", "fig5_6_code_error.png", "fig5_7_loss.png",
                          "fig5_7_excess.png", "fig5_8_loss.png", "fig5_8_excess.png", "fig5_9_bce_bars.png",
                          "fig5_9_excess.png"], since)


def _check_return(table, what, max_steps=20, episodes=3):
    """A policy's returns over the held-out games of at most `max_steps` steps: finite, at most
    5 (a few pellets' worth of length) per step either way, inside their confidence interval."""
    length = _finite(table["mean_length"], f"{what} mean_length")
    assert table["episodes"] == episodes and 1 <= length <= max_steps, (what, table)
    ret = _finite(table["mean_return"], f"{what} mean_return")
    assert abs(ret) <= 5.0 * length, (what, table)
    lo, hi = (_finite(x, f"{what} ci95") for x in table["ci95"])
    assert lo - EPS <= ret <= hi + EPS, (what, table)


def _check_controller(runs, since):
    """controller.json: the two configurations of the tiny budget on seed 0 (a model-based
    controller trained in imagination, and PPO), each an ordinary run of its configuration's
    options, and the four reference policies on the same games. (The thesis's reward ascent,
    `rollout`, is the same kind of run: tests/test_online.py trains it.)"""
    path = runs / "controller.json"
    assert path.stat().st_mtime >= since
    results = json.loads(path.read_text())
    assert results["notebook_budget"] == "tiny" and results["budget"]["seeds"] == [0]
    assert list(results["configs"]) == ["critic", "ppo"]
    max_steps = results["budget"]["episode_steps"]
    for name, r in results["configs"].items():
        seed = r["seeds"]["0"]
        length = _finite(seed["length"], f"{name} length")
        assert 1 <= length <= max_steps and abs(_finite(seed["return"], f"{name} return")) <= 5.0 * length, (name, seed)
        assert r["return"]["per_seed"] == [seed["return"]], name
        assert [frames for frames, _ in seed["curve"]] == [r["frames"]], (name, seed["curve"])
        config = upgrade(json.loads((runs / name / "seed0" / "config.json").read_text()))
        assert {k: config[k] for k in r["options"] if k in config} == {k: v for k, v in r["options"].items()
                                                                       if k in config}, (name, config)
        if name != "ppo":
            fit = seed["reward_fit"]
            assert -1.0 <= _finite(fit["correlation"], f"{name} correlation") <= 1.0 and fit["steps"] > 0, (name, fit)
    assert set(results["references"]) == {"uniform", "never_accelerate", "behaviour", "privileged"}
    for policy, row in results["references"].items():
        _check_return(row, policy, max_steps, results["budget"]["eval_episodes"])
    _check_figures(runs, ["curves.png"], since)


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
