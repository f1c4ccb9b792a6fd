"""Runs whose jitted program plays the built-in game: the controller variants (action_loop,
reward_prediction, final_proposal) trained online, PPO (`cdrl train --variant ppo`), and
`GameJob`, the host loop's job for every such program.

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
import functools
import sys
from pathlib import Path
from typing import Callable

import jax
import numpy as np

from cdrl.evaluation.metrics import excess_ratio
from cdrl.evaluation.play import EVAL_SEED, compare_policies, controller_policy, format_table
from cdrl.models import make_variant
from cdrl.runs.checkpoint import Checkpoints
from cdrl.runs.config import RunConfig
from cdrl.runs.rundir import RunDir
from cdrl.runs.sources import run_game, with_obs_norm
from cdrl.runs.writer import run_writer
from cdrl.training.loop import Job, Plan, host_loop
from cdrl.training.monitor import group_names
from cdrl.training.dream import DreamConfig, DreamHParams, DreamState, dream_step, init_dream
from cdrl.training.online import OnlineConfig, OnlineHParams, OnlineState, init_online, online_step
from cdrl.training.optim import HParams, OptHParams
from cdrl.training.ppo import PPOConfig, PPOHParams, init_ppo, ppo_policy, ppo_step


class GameJob(Job):
    """A program that plays the game as it learns: `program(state) -> (state, metrics)` with
    the game statistics every such program reports (`reward`, `episodes`, `return_sum`,
    `length_sum`, `action_mean`); `policy(state)` is the learned policy, noise-free, in the
    form of `cdrl.evaluation.play`, and `name` its row in the evaluation table. Metrics named
    in `extras` are logged as they are."""

    def __init__(self, cfg: RunConfig, program: Callable, ckpts: Checkpoints, names: list[str], name: str,
                 policy: Callable, game, env_params, extras: tuple[str, ...] = ()):
        self.cfg, self.program, self.ckpts, self.name, self.policy = cfg, program, ckpts, name, policy
        self.game, self.env_params, self.extras = game, env_params, extras
        self.desc = f"{name} {cfg.variant}"
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


def game_run(cfg: RunConfig, run: RunDir, resume: bool, init_state, job_of: Callable, progress: bool | None) -> dict:
    """The host loop of a `GameJob` in `run`: `init_state` is the fresh program state (restored
    when resuming), `job_of(checkpoints, state)` the job. Ends with the policy table on stderr."""
    opened = run.open(cfg, init_state, resume)
    job: GameJob = job_of(opened.checkpoints, opened.state)
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


def hparams(cfg: RunConfig) -> OnlineHParams:
    return OnlineHParams.create(opt=cfg.opt_hparams(), ascent=cfg.ascent, reward_weight=cfg.reward_weight,
                                noise_std=cfg.noise_std, noise_decay=cfg.noise_decay, warmup_steps=cfg.warmup_steps,
                                diverge_threshold=cfg.diverge_threshold, scope=cfg.scope)


def online_setup(cfg: RunConfig):
    """(variant, game, its parameters, static config, traced hyper-parameters) of an online run."""
    variant = make_variant(cfg.variant, cfg.arch)
    game, env_params = run_game(cfg)
    return variant, game, env_params, OnlineConfig(num_envs=cfg.batch, unroll=cfg.unroll), hparams(cfg)


def online_job(cfg: RunConfig, setup: tuple, ckpts: Checkpoints, state) -> GameJob:
    """The `GameJob` of an online run with the `online_setup(cfg)` it was built from."""
    variant, game, env_params, ocfg, hp = setup
    program = functools.partial(_online_program, variant, game, ocfg, hp, env_params)
    return GameJob(cfg, program, ckpts, group_names(state.train.params), "controller",
                   lambda s: controller_policy(variant, model_params(s)), game, env_params,
                   extras=("noise_std", "ascent_on"))


def _online_program(variant, game, ocfg, hp, env_params, state):
    return online_step(variant, game, ocfg, state, hp, env_params)


def dream_setup(cfg: RunConfig):
    """(variant, game, its parameters, static config, traced hyper-parameters) of an online run
    whose controller learns in imagination (`cdrl.training.dream`)."""
    variant = make_variant(cfg.variant, cfg.arch)
    game, env_params = run_game(cfg)
    dcfg = DreamConfig(num_envs=cfg.batch, unroll=cfg.unroll, replay=cfg.replay, model_updates=cfg.model_updates,
                       horizon=cfg.horizon, controller=cfg.controller)
    model = HParams.create(variant, opt=cfg.opt_hparams(), diverge_threshold=cfg.diverge_threshold,
                           loss_weights={"reward_mse": cfg.reward_weight} if variant.predicts_reward else None)
    hp = DreamHParams.create(model, ctrl_opt=OptHParams.create("adam", lr=cfg.ctrl_lr, grad_clip=100.0),
                             ascent=cfg.ascent, explore=cfg.noise_std, explore_decay=cfg.noise_decay,
                             warmup_steps=cfg.warmup_steps, gamma=cfg.gamma, lam=cfg.gae_lambda,
                             entropy=cfg.entropy_coef)
    return variant, game, env_params, dcfg, hp


def dream_job(cfg: RunConfig, setup: tuple, ckpts: Checkpoints, state) -> GameJob:
    variant, game, env_params, dcfg, hp = setup
    program = functools.partial(_dream_program, variant, game, dcfg, hp, env_params)
    return GameJob(cfg, program, ckpts, group_names(state.model.params), "controller",
                   lambda s: controller_policy(variant, model_params(s)), game, env_params,
                   extras=("explore", "controller_on"))


def _dream_program(variant, game, dcfg, hp, env_params, state):
    return dream_step(variant, game, dcfg, state, hp, env_params)


def learner(cfg: RunConfig):
    """(setup, fresh state of the program, job maker) of a run that plays the game."""
    if cfg.kind == "ppo":
        setup = ppo_setup(cfg)
        arch, game, env_params, pcfg, hp = setup
        return setup, lambda: init_ppo(arch, game, env_params, pcfg, jax.random.PRNGKey(cfg.seed), hp), ppo_job
    if cfg.controller == "rollout":
        setup = online_setup(cfg)
        variant, game, env_params, ocfg, hp = setup
        return setup, lambda: init_online(variant, game, env_params, ocfg, jax.random.PRNGKey(cfg.seed), hp), online_job
    setup = dream_setup(cfg)
    variant, game, env_params, dcfg, hp = setup
    return setup, lambda: init_dream(variant, game, env_params, dcfg, jax.random.PRNGKey(cfg.seed), hp), dream_job


def model_params(state):
    """The world model's parameters (the controller's included) of an online program's state."""
    if isinstance(state, DreamState):
        return state.model.params
    if isinstance(state, OnlineState):
        return state.train.params
    raise TypeError(f"{type(state).__name__} holds no world model")


def online_train_run(cfg: RunConfig, run: RunDir, resume: bool, progress: bool | None = None) -> dict:
    """A controller variant, or PPO, trained against the game in `run`."""
    if not resume:
        cfg = with_obs_norm(cfg, run.data_cache)
    setup, fresh, job_of = learner(cfg)
    return game_run(cfg, run, resume, fresh(), lambda ckpts, s: job_of(cfg, setup, ckpts, s), progress)


def ppo_setup(cfg: RunConfig):
    """(architecture, game, its parameters, static config, traced hyper-parameters) of a PPO run."""
    game, env_params = run_game(cfg)
    pcfg = PPOConfig(num_envs=cfg.batch, unroll=cfg.unroll, epochs=cfg.ppo_epochs, minibatches=cfg.ppo_minibatches)
    hp = PPOHParams.create(opt=cfg.opt_hparams(), gamma=cfg.gamma, gae_lambda=cfg.gae_lambda, clip_eps=cfg.clip_eps,
                           value_coef=cfg.value_coef, entropy_coef=cfg.entropy_coef,
                           diverge_threshold=cfg.diverge_threshold)
    return cfg.arch, game, env_params, pcfg, hp


def ppo_job(cfg: RunConfig, setup: tuple, ckpts: Checkpoints, state) -> GameJob:
    arch, game, env_params, pcfg, hp = setup
    program = functools.partial(_ppo_program, arch, game, pcfg, hp, env_params)
    return GameJob(cfg, program, ckpts, group_names(state.params), "ppo", lambda s: ppo_policy(arch, s.params),
                   game, env_params)


def _ppo_program(arch, game, pcfg, hp, env_params, state):
    return ppo_step(arch, game, pcfg, state, hp, env_params)


def eval_policy_run(run_dir: Path, episodes: int | None = None, seed: int = EVAL_SEED) -> dict[str, dict]:
    """`cdrl eval --policy RUN_DIR`: the run's learned policy (latest good checkpoint, no noise:
    a controller, or PPO's greedy policy) against the reference policies on the same held-out
    games."""
    run = RunDir(run_dir)
    cfg = run.read_config()
    if cfg.kind == "offline":
        raise ValueError(f"run {run.path} trains {cfg.variant!r}, which has no controller to play with")
    setup, fresh, job_of = learner(cfg)
    state, _, warnings = run.read_checkpoints().restore_latest_good(jax.eval_shape(fresh))
    for w in warnings:
        print(f"warning: {w}; using an older checkpoint", file=sys.stderr)
    return job_of(cfg, setup, run.read_checkpoints(), state).play(state, episodes, seed)
