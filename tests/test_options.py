"""The options: each defined once, in one section, with one default that every learner's own
numbers take; `config.json` nested by section; flat configs and old names still load, and a
run written in the old format resumes exactly."""
import dataclasses
import json

import numpy as np

from cdrl.learners.ppo import PPOHParams
from cdrl.learners.replay_base import ReplayHParams
from cdrl.learners.thesis_ascent import AscentHParams
from cdrl.models import TINY, make_variant
from cdrl.options import SECTIONS
from cdrl.runs.config import RunConfig, saved_config, upgrade
from cdrl.runs.grid import GRID_FIELDS
from cdrl.runs.train import train_run
from cdrl.training.optim import HParams


def test_every_option_is_defined_once_in_one_section():
    names = [f.name for cls in SECTIONS.values() for f in dataclasses.fields(cls)]
    assert len(names) == len(set(names))
    assert [f.name for f in dataclasses.fields(RunConfig)] == names
    traced = {f.name for f in dataclasses.fields(RunConfig) if f.metadata["traced"]}
    assert set(GRID_FIELDS) <= traced  # a sweep varies traced numbers only


def test_the_learners_numbers_default_to_the_runs():
    """Built with no arguments, each learner's traced numbers are those a run gets by default."""
    run = RunConfig(variant="final_proposal", learner="imagination_ac")
    replay = ReplayHParams.create(HParams.create(make_variant("final_proposal", TINY)))
    for got, want in ((replay.ascent, run.ascent), (replay.explore, run.noise_std), (replay.gamma, run.gamma),
                      (replay.lam, run.gae_lambda), (replay.entropy, run.entropy_coef), (replay.clip_eps, run.clip_eps),
                      (replay.ctrl_opt.lr, run.ctrl_lr), (replay.warmup_steps, run.warmup_steps)):
        assert float(got) == np.float32(want)
    ascent, run = AscentHParams.create(), RunConfig(variant="final_proposal")
    for got, want in ((ascent.opt.lr, run.lr), (ascent.opt.momentum, run.momentum), (ascent.ascent, run.ascent),
                      (ascent.reward_weight, run.reward_weight), (ascent.noise_std, run.noise_std),
                      (ascent.diverge_threshold, run.diverge_threshold)):
        assert float(got) == np.float32(want)
    ppo, run = PPOHParams.create(), RunConfig(learner="ppo")
    for got, want in ((ppo.opt.lr, run.lr), (ppo.opt.grad_clip, run.grad_clip), (ppo.gamma, run.gamma),
                      (ppo.clip_eps, run.clip_eps), (ppo.value_coef, run.value_coef),
                      (ppo.entropy_coef, run.entropy_coef)):
        assert float(got) == np.float32(want)


def test_config_json_is_nested_and_old_forms_load():
    cfg = RunConfig(variant="final_proposal", learner="onpolicy_ac", preset="small", max_filter=5, lr=0.5)
    nested = cfg.to_dict()
    assert list(nested) == list(SECTIONS) and nested["optim"]["lr"] == 0.5 and nested["control"]["learner"] == "onpolicy_ac"
    assert saved_config(nested) == cfg
    assert saved_config(dataclasses.asdict(cfg)) == cfg  # flat, as older versions wrote it
    old = {**dataclasses.asdict(cfg), "controller": "real", "preset": "small-max", "recipe": "fast"}
    del old["learner"], old["max_filter"]
    assert saved_config(old) == cfg
    assert RunConfig(preset="small-max").arch == RunConfig(preset="small", max_filter=5).arch
    assert upgrade({"variant": "ppo"}) == {"variant": "main", "learner": "ppo"}


def _run(run_dir, steps, resume=False):
    cfg = None if resume else RunConfig(variant="main", preset="tiny", data="synthetic", episodes=8, episode_steps=40,
                                        steps=steps, lr=1.0, batch=2, unroll=8, checkpoint_every=2, eval_every=0,
                                        tensorboard=False)
    train_run(cfg, run_dir, resume=resume, overrides={"steps": steps} if resume else None, progress=False)
    return [json.loads(line)["loss"] for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def test_a_run_written_flat_under_old_names_resumes_exactly(tmp_path):
    straight = _run(tmp_path / "straight", 4)
    _run(tmp_path / "old", 2)
    config = tmp_path / "old" / "config.json"
    flat = upgrade(json.loads(config.read_text()))
    config.write_text(json.dumps({**{k: v for k, v in flat.items() if k != "learner"}, "recipe": "fast",
                                  "controller": "rollout"}))
    assert _run(tmp_path / "old", 4, resume=True) == straight
    assert "schedule" in json.loads(config.read_text())  # rewritten nested by the resume
