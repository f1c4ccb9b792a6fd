"""Runs whose jitted program plays the built-in game: any learner of `cdrl.learners` (the
controller variants' learners, PPO, a user's own), and `GameJob`, the host loop's job for
every such learner.

The run directory has the layout of offline runs; `metrics.jsonl` lines add the real reward
per game step, the finished episodes' mean return, the mean executed action and what the
program reports besides (the exploration noise, whether the ascent is on, and for world
models the excess ratio of the chunk's next-frame predictions against copying the last frame,
on the frames the model is about to learn from, so before the update). Each evaluation plays
the learned policy without noise against the reference policies on the same held-out games
(`cdrl.evaluation.play.compare_policies`). Checkpoints hold the whole program state (games
included), so a resumed run continues exactly.
"""
from __future__ import annotations

import contextlib
import dataclasses
import sys
from pathlib import Path
from typing import Any

import jax
import numpy as np

from cdrl import learners
from cdrl.evaluation.metrics import check_episodes, excess_ratio
from cdrl.evaluation.play import EVAL_SEED, compare_policies, format_table
from cdrl.learners.api import Learner, train_program
from cdrl.models import make_variant
from cdrl.runs.checkpoint import Checkpoints
from cdrl.runs.config import RunConfig
from cdrl.runs.rundir import RunDir
from cdrl.runs.sources import run_game, with_obs_norm
from cdrl.runs.record_sinks import run_writer
from cdrl.training.loop import Job, Plan, host_loop
from cdrl.training.monitor import group_names


class GameJob(Job):
    """A program that plays the game as it learns: `program(state) -> (state, metrics)` with
    the game statistics every such program reports (`reward`, `episodes`, `return_sum`,
    `length_sum`, `action_mean`); `policy(state)` is the learned policy, noise-free, in the
    form of `cdrl.evaluation.play`, and `name` its row in the evaluation table. Metrics named
    in `extras` are logged as they are."""

    def __init__(self, cfg: RunConfig, learner: Learner, ckpts: Checkpoints, names: list[str]):
        self.cfg, self.learner, self.ckpts, self.name = cfg, learner, ckpts, learner.row
        self.program = lambda state: train_program(learner, state)
        self.policy = learner.policy
        self.game, self.env_params, self.extras = learner.game, learner.env_params, learner.extras
        self.desc = f"{learner.name} {cfg.variant}" if learner.has_world_model else learner.name
        self.frames_per_step = cfg.batch * cfg.unroll
        self.ratio_names = names
        self.threshold = cfg.diverge_threshold
        self.reference_rows: dict | None = None  # the reference policies' rows: the same games every time

    def step(self, state):
        return self.program(state)

    def record(self, m: dict) -> dict:
        episodes = int(m["episodes"])
        fields = {"reward": float(m["reward"]), "episodes": episodes,
                  "mean_return": float(m["return_sum"]) / episodes if episodes else None,
                  "mean_length": float(m["length_sum"]) / episodes if episodes else None,
                  "action_mean": np.asarray(m["action_mean"]).tolist()}
        terms = m["terms"]
        if "obs_bce" in terms:
            fields["excess_ratio"] = excess_ratio(float(terms["obs_bce"]), float(terms["copy_bce"]),
                                                  float(terms["target_entropy"]))
        for name in self.extras:
            value = np.asarray(m[name])
            fields[name] = value.item() if value.ndim == 0 else value.tolist()
        return fields

    def play(self, state, episodes: int | None = None, seed: int = EVAL_SEED) -> dict[str, dict]:
        """The learned policy's row and the reference policies' on the same held-out games."""
        episodes = episodes or self.cfg.eval_episodes
        rows = compare_policies(self.game, self.env_params, {self.name: self.policy(state)}, episodes,
                                self.cfg.episode_steps, seed, references=self.reference_rows is None)
        if self.reference_rows is None:
            self.reference_rows = {k: v for k, v in rows.items() if k != self.name}
        return {self.name: rows[self.name], **self.reference_rows}

    def evaluate(self, step, state, lanes):
        return {0: ({"step": step, "split": "play", "policies": self.play(state)}, None)} if lanes else {}

    def save(self, step, state, saves, alive, diverged):
        self.ckpts.save(step, state, {"step": step, "config": dataclasses.asdict(self.cfg)})
        return str(self.ckpts.directory / str(step))

    def postfix(self, records):
        return {"loss": f"{records[0]['loss']:.4f}", "reward": f"{records[0]['reward']:.3f}"}


def build_learner(cfg: RunConfig) -> Learner:
    """The learner a run of `cfg` plays the game with (`cfg.learner`, from the registry), its
    model built from the run's variant and preset (a model-free learner gets the preset's
    architecture), its game from the run's level."""
    game, env_params = run_game(cfg)
    cls = learners.learner_class(cfg.learner)
    model = make_variant(cfg.variant, cfg.arch) if cls.has_world_model else cfg.arch
    return cls.from_run(cfg, model, game, env_params)


def game_job(cfg: RunConfig, learner: Learner, ckpts: Checkpoints, state) -> GameJob:
    return GameJob(cfg, learner, ckpts, group_names(learner.watched(state)))


def online_train_run(cfg: RunConfig, run: RunDir, resume: bool, progress: bool | None = None,
                     allow_data_change: bool = False, init_params=None) -> dict:
    """A learner trained against the game in `run`; ends with the policy
    table on stderr. `init_params`: the world model's parameters to start from (`--init-from`).
    (It plays the game: there is no data set to change, so `allow_data_change` has nothing to
    allow.)"""
    if not resume:
        cfg = with_obs_norm(cfg, run.data_cache)
    learner = build_learner(cfg)
    state = learner.init(jax.random.PRNGKey(cfg.seed))
    if init_params is not None:
        state = learner.with_world_model(state, init_params)
    opened = run.open(cfg, state, resume)
    job = game_job(cfg, learner, opened.checkpoints, opened.state)
    plan = Plan(steps=cfg.steps, start=opened.start, eval_every=cfg.eval_every, checkpoint_every=cfg.checkpoint_every)
    sink = run_writer(run, opened.start, cfg.tensorboard)
    with contextlib.closing(sink):
        result = host_loop(job, opened.state, plan, [sink], progress=sys.stderr.isatty() if progress is None else progress)
        if 0 in result.last_eval:
            rows = result.last_eval[0]["policies"]
        else:  # a finished run resumed: play it again
            rows = job.play(result.state)
    print(format_table(rows), file=sys.stderr)
    return {"run_dir": str(run.path), "steps": cfg.steps, "policies": rows}


def restore_learner(run: RunDir) -> tuple[RunConfig, Learner, Any]:
    """(config, learner, state of the latest good checkpoint) of a run that plays the game."""
    cfg = run.read_config()
    if cfg.kind == "offline":
        if make_variant(cfg.variant, cfg.arch).has_controller:
            raise ValueError(f"run {run.path} trains the world model of {cfg.variant!r} offline (learner world_model), "
                             "so it has no controller to play with; train one from it with --init-from")
        raise ValueError(f"run {run.path} trains {cfg.variant!r}, which has no controller to play with")
    learner = build_learner(cfg)
    state, _ = run.read_checkpoints().restore_newest(jax.eval_shape(lambda: learner.init(jax.random.PRNGKey(cfg.seed))))
    return cfg, learner, state


def eval_policy_run(run_dir: Path, episodes: int | None = None, seed: int = EVAL_SEED) -> dict[str, dict]:
    """`cdrl eval --policy RUN_DIR`: the run's learned policy (latest good checkpoint, no noise:
    a controller, or PPO's greedy policy) against the reference policies on the same held-out
    games."""
    check_episodes(episodes)
    run = RunDir(run_dir)
    cfg, learner, state = restore_learner(run)
    return game_job(cfg, learner, run.read_checkpoints(), state).play(state, episodes, seed)
