"""Controller runs (PPO and the controller trained in imagination) through the CLI: resumed runs
equal straight ones, `cdrl eval --policy` plays them, and a world model learnt offline starts a
controller run. (Apart from `test_control.py` so that the two test workers share the load.)"""
import json
import math

import jax
import numpy as np
import pytest

from cdrl.evaluation import play
from cdrl.models import make_variant

RUN = ["--preset", "tiny", "--batch", "4", "--unroll", "4", "--episode-steps", "30", "--eval-every", "0",
       "--eval-episodes", "3", "--checkpoint-every", "2", "--no-tensorboard"]


def _losses(run_dir):
    return [json.loads(line)["loss"] for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


@pytest.mark.parametrize("learner", [pytest.param(["--variant", "ppo"], marks=pytest.mark.e2e),
                                     ["--variant", "final_proposal", "--controller", "critic", "--replay", "4",
                                      "--horizon", "3", "--model-updates", "2", "--warmup-steps", "1",
                                      "--lookahead-steps", "2"]],
                         ids=["ppo", "critic"])
def test_learners_are_runs_that_resume_exactly(tmp_path, capsys, learner):
    """PPO and the controller trained in imagination (its world model with the look-ahead
    losses) are runs like any other: config, metrics, checkpoints; a run stopped at a checkpoint
    and resumed gives the straight run's losses, and `cdrl eval --policy` plays its policy
    against the references on the same games."""
    from cdrl.cli import main

    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    assert main(["train", "--run-dir", str(straight), *learner, *RUN, "--steps", "4"]) == 0
    assert main(["train", "--run-dir", str(resumed), *learner, *RUN, "--steps", "2"]) == 0
    assert main(["train", "--resume", str(resumed), "--steps", "4"]) == 0
    a, b = _losses(straight), _losses(resumed)
    assert len(a) == len(b) == 4 and max(abs(x - y) for x, y in zip(a, b)) <= 1e-6, (a, b)
    if "--lookahead-steps" in learner:  # the model's updates take every look-ahead term
        terms = json.loads((resumed / "metrics.jsonl").read_text().splitlines()[-1])["terms"]
        assert all(math.isfinite(terms[f"model_{t}"]) for t in ("imag_obs_bce", "reward_twohot", "cont_bce",
                                                                 "value_twohot"))
    capsys.readouterr()
    video = ["--video"] if "ppo" in learner else []  # the end-to-end tier writes a game of the policy too
    assert main(["eval", "--policy", str(straight), "--episodes", "3", *video]) == 0
    out = capsys.readouterr().out
    name = "ppo" if "ppo" in learner else "controller"
    assert all(row in out for row in (name, *play.REFERENCES))
    if video:
        from PIL import Image

        assert f"wrote {straight / 'policy.gif'}" in out and Image.open(straight / "policy.gif").n_frames > 1


@pytest.mark.e2e
def test_a_world_model_learnt_offline_starts_a_controller_run(tmp_path, capsys):
    """`--controller none` trains a controller variant offline on recorded episodes (the reward
    terms off by default, weighted by `reward_weight` and `reward_balanced_weight` when set);
    `--init-from` starts a controller run from that model, with its input normalisation; a model
    of another variant is refused, naming both."""
    import json

    from cdrl.cli import main
    from cdrl.runs.config import RunConfig
    from cdrl.runs.init_from import restore_params
    from cdrl.runs.rundir import RunDir

    src, dst = tmp_path / "src", tmp_path / "dst"
    offline = ["--variant", "final_proposal", "--preset", "tiny", "--episodes", "6", "--episode-steps", "30",
               "--batch", "2", "--unroll", "4", "--eval-every", "0", "--eval-episodes", "1", "--no-tensorboard"]
    assert main(["train", "--run-dir", str(src), "--controller", "none", *offline, "--steps", "3",
                 "--reward-weight", "0.25", "--reward-balanced-weight", "0.5"]) == 0
    cfg = RunDir(src).read_config()
    assert cfg.kind == "offline" and cfg.obs_norm == "data" and cfg.obs_std != 1.0
    assert RunConfig(variant="final_proposal", controller="none").reward_weight == 0.0
    first = json.loads((src / "metrics.jsonl").read_text().splitlines()[0])
    terms = first["terms"]
    weighted = terms["obs_bce"] + 0.25 * terms["reward_mse"] + 0.5 * terms["reward_balanced"]
    assert first["loss"] == pytest.approx(weighted, rel=1e-5)
    assert terms["reward_balanced"] != pytest.approx(terms["reward_mse"], rel=1e-3)
    learnt = restore_params(RunDir(src))[1]
    # an SGD step of 1e-12 leaves the observation path where the source left it
    assert main(["train", "--run-dir", str(dst), "--variant", "final_proposal", "--controller", "critic",
                 "--replay", "4", "--horizon", "3", "--model-updates", "2", "--warmup-steps", "1", *RUN,
                 "--steps", "1", "--optimizer", "sgd", "--lr", "1e-12", "--init-from", str(src)]) == 0
    started = RunDir(dst).read_config()
    assert (started.obs_mean, started.obs_std) == (cfg.obs_mean, cfg.obs_std)
    after = restore_params(RunDir(dst))[1]
    fresh = make_variant("final_proposal", started.arch).init(jax.random.PRNGKey(started.seed))
    for name in ("obs_enc", "lstm", "obs_dec"):
        for a, b, c in zip(jax.tree.leaves(after[name]), jax.tree.leaves(learnt[name]), jax.tree.leaves(fresh[name])):
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-9)
        assert any(not np.allclose(b, c) for b, c in zip(jax.tree.leaves(learnt[name]), jax.tree.leaves(fresh[name])))
    capsys.readouterr()
    assert main(["train", "--run-dir", str(tmp_path / "other"), "--variant", "reward_prediction", *RUN,
                 "--steps", "1", "--init-from", str(src)]) == 2
    err = capsys.readouterr().err
    assert "variant 'final_proposal'" in err and "'reward_prediction'" in err
    assert not (tmp_path / "other" / "config.json").exists()
