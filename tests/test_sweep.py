"""Sweeps: one vmapped program equals the separate runs; divergence stops one config only;
the learning-rate search rejects the rate that blows up and names the group."""
import dataclasses
import json

import numpy as np
import pytest

from cdrl.cli import main as cli_main
from cdrl.analysis.plots import plot_sweep
from cdrl.runs.config import RunConfig
from cdrl.runs.sweep import Grid, lr_search, sweep_run
from cdrl.runs.train import train_run

BASE = dict(preset="tiny", data="synthetic", episodes=6, episode_steps=20, unroll=4, batch=2,
            steps=6, eval_every=0, eval_episodes=1, checkpoint_every=3)


def records(run_dir):
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def losses(run_dir):
    return [r["loss"] for r in records(run_dir)]


@pytest.mark.parametrize("variant", ["baseline_recurrent"])  # two stages; the stage switch must match too
def test_two_config_sweep_equals_two_runs(tmp_path, variant):
    base = RunConfig(variant=variant, **BASE)
    grid = Grid(lr=(0.1, 0.03), momentum=(0.9,), seed=(0, 1))
    rows = sweep_run(base, grid, tmp_path / "sweep", progress=False)
    assert len(rows) == 4
    for row in rows[:: 3]:  # (lr 0.1, seed 0) and (lr 0.03, seed 1): lr, init and data order all differ
        cfg = RunConfig(variant=variant, lr=row["lr"], seed=row["seed"], **BASE)
        single = tmp_path / f"single-{row['name']}"
        summary = train_run(cfg, single, progress=False)
        np.testing.assert_allclose(losses(tmp_path / "sweep" / row["name"]), losses(single), rtol=2e-5, atol=1e-6)
        assert row["test_bce"] == pytest.approx(summary["final_eval"]["bce"], rel=1e-4)
    assert losses(tmp_path / "sweep" / rows[0]["name"]) != losses(tmp_path / "sweep" / rows[1]["name"])
    assert plot_sweep(tmp_path / "sweep").stat().st_size > 0
    assert "| lr0.1-mom0.9-seed0-thr1000 |" in (tmp_path / "sweep" / "results.md").read_text()


def test_sweep_config_resumes_as_a_run(tmp_path):
    """Each config's directory is an ordinary run: `cdrl train --resume` continues it exactly
    as the single run would have gone on."""
    base = RunConfig(variant="main", **BASE)
    rows = sweep_run(base, Grid(lr=(0.1, 0.05)), tmp_path / "sweep", progress=False)
    swept = records(tmp_path / "sweep" / rows[1]["name"])
    assert [r["step"] for r in swept] == list(range(6))
    cont = train_run(None, rows[1]["run_dir"], resume=True, overrides={"steps": 9}, progress=False)
    full = tmp_path / "full"
    train_run(RunConfig(variant="main", lr=0.05, **{**BASE, "steps": 9}), full, progress=False)
    assert cont["steps"] == 9
    np.testing.assert_allclose(losses(tmp_path / "sweep" / rows[1]["name"]), losses(full), rtol=2e-5, atol=1e-6)
    # It went on from the sweep's checkpoint at step 6 (a run started over would match the
    # losses too): the sweep's records of steps 0-5 are kept as they were, frames/s (a
    # wall-clock measurement) included.
    after = records(tmp_path / "sweep" / rows[1]["name"])
    assert [r["step"] for r in after] == list(range(9)) and after[:6] == swept


def test_diverging_config_stops_alone(tmp_path):
    base = RunConfig(variant="main", **BASE)
    rows = sweep_run(base, Grid(lr=(0.05, 1e4)), tmp_path / "sweep", progress=False)
    good, bad = rows
    assert good["diverged_at"] is None and len(losses(tmp_path / "sweep" / good["name"])) == BASE["steps"]
    assert bad["diverged_at"] is not None and bad["diverged_group"]
    assert len(losses(tmp_path / "sweep" / bad["name"])) == bad["diverged_at"]
    assert bad["test_bce"] is not None and np.isfinite(bad["test_bce"])  # the last good parameters


def test_lr_search_picks_highest_stable_rate():
    base = RunConfig(variant="main", **BASE)
    result = lr_search(base, candidates=[1e4, 0.1, 0.01], probe_steps=4, threshold=10.0, progress=False)
    by_lr = {c["lr"]: c for c in result["candidates"]}
    assert result["chosen"] == 0.1
    assert by_lr[1e4]["rejected"] is not None and "/" in by_lr[1e4]["rejected"]["group"]
    assert by_lr[0.1]["rejected"] is None and by_lr[0.1]["max_ratio"] <= 10.0


def test_lr_search_over_seeds_probes_each_seed_and_needs_them_all(tmp_path):
    """Each seed probed as its own single-seed search would be (own initialisation and data);
    with the threshold between two seeds' largest ratios at a rate, that rate fails as a whole."""
    base = RunConfig(variant="main", **BASE, recipe="thesis")  # raw input: no per-seed normalisation
    lrs = [1e4, 0.5, 0.01]
    alone = {s: lr_search(dataclasses.replace(base, seed=s), lrs, 4, 1e9, progress=False, data_cache=tmp_path)
             for s in (0, 1)}
    both = lr_search(base, lrs, 4, 1e9, progress=False, data_cache=tmp_path, seeds=(0, 1))
    for c in both["candidates"]:
        for run in c["per_seed"]:
            single = next(a for a in alone[run["seed"]]["candidates"] if a["lr"] == c["lr"])
            assert run["max_ratio"] == pytest.approx(single["max_ratio"], rel=1e-5)
    ratios = {s: next(a for a in alone[s]["candidates"] if a["lr"] == 0.5)["max_ratio"] for s in (0, 1)}
    assert ratios[0] != ratios[1]
    between = (ratios[0] + ratios[1]) / 2
    worse = max(ratios, key=ratios.get)
    split = lr_search(base, lrs, 4, between, progress=False, data_cache=tmp_path, seeds=(0, 1))
    by_lr = {c["lr"]: c for c in split["candidates"]}
    assert by_lr[0.5]["rejected"]["seed"] == worse
    assert [r["rejected"] is None for r in by_lr[0.5]["per_seed"]] == [s != worse for s in (0, 1)]
    assert split["chosen"] == 0.01 and split["seeds"] == [0, 1]
    with pytest.raises(ValueError, match="repeat"):
        lr_search(base, lrs, 4, 1.0, progress=False, data_cache=tmp_path, seeds=(1, 1))


def test_sweep_cli_and_bad_input(tmp_path, capsys):
    assert cli_main(["sweep", "--run-dir", str(tmp_path / "s"), "--variant", "final_proposal", "--preset", "tiny",
                     "--devices", "2"]) == 2
    assert "online sweep runs on one device" in capsys.readouterr().err
    with pytest.raises(ValueError, match="repeats a value of lr"):
        Grid(lr=(0.1, 0.1))
    with pytest.raises(ValueError, match="lr must be > 0"):
        sweep_run(RunConfig(variant="main", **BASE), Grid(lr=(0.1, -1.0)), tmp_path / "x", progress=False)
