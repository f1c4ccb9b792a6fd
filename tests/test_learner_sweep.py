"""Online sweeps: every lane of one vmapped program equals the same configuration trained
alone; a lane that diverges stops while the other goes on; `cdrl sweep` of a learner writes a
run directory per configuration."""
import json

import jax
import numpy as np
import pytest

from cdrl.cli import main as cli_main
from cdrl.learners.api import train_program
from cdrl.runs.config import RunConfig
from cdrl.runs.grid import Grid, take
from cdrl.runs.learner_sweep import run_lanes, stack_learners
from cdrl.runs.online import build_learner
from cdrl.runs.rundir import RunDir
from cdrl.training.loop import Sink

TINY = dict(preset="tiny", batch=2, unroll=4, episode_steps=20, eval_every=0, eval_episodes=1)
LEARNERS = {"ppo": dict(learner="ppo", ppo_epochs=1, ppo_minibatches=2),
            "onpolicy_ac": dict(learner="onpolicy_ac", variant="final_proposal", replay=2, model_updates=1,
                                ppo_epochs=1)}
STEPS = 3


def alone(cfg: RunConfig, steps: int) -> list[dict]:
    """The host metrics of `steps` steps of `cfg` trained by itself (`train_program`)."""
    learner = build_learner(cfg)
    state = learner.init(jax.random.PRNGKey(cfg.seed))
    out = []
    for _ in range(steps):
        state, metrics = train_program(learner, state)
        out.append(jax.device_get(metrics))
    return out


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.e2e) if n != "ppo" else n for n in sorted(LEARNERS)])
def test_lanes_equal_single_runs(name):
    cfgs = Grid(seed=(0, 1)).configs(RunConfig(**TINY, **LEARNERS[name]))
    sinks = [Sink(), Sink()]
    result = run_lanes(cfgs, STEPS, sinks)
    assert result.alive == [True, True] and not result.diverged
    for cfg, sink in zip(cfgs, sinks):
        single = alone(cfg, STEPS)
        assert [r["step"] for r in sink.steps] == list(range(STEPS))
        for swept, m in zip(sink.steps, single):
            # The vmapped convolutions may sum in another order: equal up to float rounding.
            np.testing.assert_allclose(swept["loss"], float(m["loss"]), rtol=1e-5, atol=1e-6)
            np.testing.assert_allclose(swept["reward"], float(m["reward"]), rtol=1e-5, atol=1e-6)
            assert swept["episodes"] == int(m["episodes"])
            np.testing.assert_allclose(swept["action_mean"], np.asarray(m["action_mean"]), rtol=1e-5, atol=1e-6)
    losses = [[r["loss"] for r in s.steps] for s in sinks]
    assert losses[0] != losses[1]  # two seeds, two runs


def test_diverging_lane_stops_alone():
    cfgs = Grid(diverge_threshold=(1e-9, 1e6)).configs(RunConfig(**TINY, **LEARNERS["ppo"]))
    _, built = stack_learners(cfgs)
    start = built[0].init(jax.random.PRNGKey(cfgs[0].seed))
    sinks = [Sink(), Sink()]
    result = run_lanes(cfgs, STEPS, sinks)
    assert result.alive == [False, True]
    assert result.diverged[0].step == 0 and result.diverged[0].finite
    assert sinks[0].steps == [] and len(sinks[1].steps) == STEPS
    kept = take(result.state, 0)  # the diverged lane keeps the state it started from
    assert all(jax.tree.leaves(jax.tree.map(lambda a, b: np.array_equal(np.asarray(a), np.asarray(b)),
                                            kept.params, start.params)))
    single = alone(cfgs[1], STEPS)
    np.testing.assert_allclose([r["loss"] for r in sinks[1].steps], [float(m["loss"]) for m in single],
                               rtol=1e-5, atol=1e-6)


def test_static_options_refused():
    base = RunConfig(**TINY, **LEARNERS["ppo"])
    with pytest.raises(ValueError, match="batch"):
        stack_learners([base, RunConfig(**{**TINY, "batch": 4}, **LEARNERS["ppo"])])
    with pytest.raises(ValueError, match="no traced number for option.*ctrl_lr"):
        stack_learners([base, RunConfig(**TINY, **LEARNERS["ppo"], ctrl_lr=1e-3)])


@pytest.mark.e2e
def test_sweep_cli_of_ppo(tmp_path, capsys):
    sweep = tmp_path / "s"
    args = ["sweep", "--run-dir", str(sweep), "--learner", "ppo", "--preset", "tiny", "--batch", "2", "--unroll", "4",
            "--ppo-epochs", "1", "--ppo-minibatches", "2", "--episode-steps", "20", "--steps", "2",
            "--eval-every", "0", "--eval-episodes", "1", "--checkpoint-every", "1", "--seed", "0", "1"]
    assert cli_main(args) == 0
    results = json.loads((sweep / "results.json").read_text())
    assert results["configs"] == 2 and results["learner"] == "ppo"
    for row in results["rows"]:
        run = sweep / row["name"]
        assert RunDir(run).read_config().seed == row["seed"]
        assert [json.loads(line)["step"] for line in (run / "metrics.jsonl").read_text().splitlines()] == [0, 1]
        evals = [json.loads(line) for line in (run / "eval.jsonl").read_text().splitlines()]
        assert evals[-1]["step"] == 2 and "ppo" in evals[-1]["policies"]
        assert row["play_return"] == evals[-1]["policies"]["ppo"]["mean_return"]
        assert sorted(p.name for p in (run / "checkpoints").iterdir() if p.name.isdigit()) == ["1", "2"]
    assert "play return" in capsys.readouterr().out
    assert cli_main(args) == 2  # the directory holds a sweep
    assert cli_main(["eval", "--policy", str(sweep / results["rows"][0]["name"]), "--episodes", "1"]) == 0
