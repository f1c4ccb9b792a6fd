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
import sys
from pathlib import Path
from typing import Any, Callable

import jax
import numpy as np

from cdrl.evaluation.metrics import check_episodes, excess_ratio
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
from cdrl.training.optim import OptHParams
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


@dataclasses.dataclass(frozen=True)
class Learner:
    """A program that plays the game as it learns, as a run builds it from its config: its
    model (a variant, or PPO's architecture), the game and its parameters, the program's static
    config and traced hyper-parameters, its `init` and jitted `step` (each called as
    `fn(model, game, config, ..., hp, env_params)`), the name of its policy's row, the policy of
    a state (noise-free, in the form of `cdrl.evaluation.play`), the state's parameters whose
    norm ratios are logged, and the metrics its records add."""

    model: Any
    game: Any
    env_params: Any
    config: Any
    hp: Any
    init: Callable
    step: Callable
    name: str
    policy: Callable
    params: Callable
    extras: tuple[str, ...] = ()

    def fresh(self, seed: int):
        return self.init(self.model, self.game, self.env_params, self.config, jax.random.PRNGKey(seed), self.hp)

    def program(self, state):
        return self.step(self.model, self.game, self.config, state, self.hp, self.env_params)

    def job(self, cfg: RunConfig, ckpts: Checkpoints, state) -> GameJob:
        return GameJob(cfg, self.program, ckpts, group_names(self.params(state)), self.name,
                       lambda s: self.policy(self.model, self.params(s)), self.game, self.env_params, self.extras)


def learner(cfg: RunConfig) -> Learner:
    """The program a run of `cfg` plays the game with: PPO, the thesis's online learner
    (`--controller rollout`), or the learner with a replay buffer and imagination."""
    game, env_params = run_game(cfg)
    if cfg.kind == "ppo":
        pcfg = PPOConfig(num_envs=cfg.batch, unroll=cfg.unroll, epochs=cfg.ppo_epochs,
                         minibatches=cfg.ppo_minibatches)
        hp = PPOHParams.create(opt=cfg.opt_hparams(), gamma=cfg.gamma, gae_lambda=cfg.gae_lambda,
                               clip_eps=cfg.clip_eps, value_coef=cfg.value_coef, entropy_coef=cfg.entropy_coef,
                               diverge_threshold=cfg.diverge_threshold)
        return Learner(cfg.arch, game, env_params, pcfg, hp, init_ppo, ppo_step, "ppo", ppo_policy,
                       lambda s: s.params)
    variant = make_variant(cfg.variant, cfg.arch)
    if cfg.controller == "rollout":
        hp = OnlineHParams.create(opt=cfg.opt_hparams(), ascent=cfg.ascent, reward_weight=cfg.reward_weight,
                                  noise_std=cfg.noise_std, noise_decay=cfg.noise_decay,
                                  warmup_steps=cfg.warmup_steps, diverge_threshold=cfg.diverge_threshold,
                                  scope=cfg.scope)
        return Learner(variant, game, env_params, OnlineConfig(num_envs=cfg.batch, unroll=cfg.unroll), hp,
                       init_online, online_step, "controller", controller_policy, model_params,
                       ("noise_std", "ascent_on"))
    dcfg = DreamConfig(num_envs=cfg.batch, unroll=cfg.unroll, replay=cfg.replay, model_updates=cfg.model_updates,
                       horizon=cfg.horizon, controller=cfg.controller, epochs=cfg.ppo_epochs,
                       scope=cfg.scope if cfg.controller == "real" else "controller")
    hp = DreamHParams.create(cfg.hparams(variant), ctrl_opt=OptHParams.create("adam", lr=cfg.ctrl_lr, grad_clip=100.0),
                             ascent=cfg.ascent, explore=cfg.noise_std, explore_decay=cfg.noise_decay,
                             warmup_steps=cfg.warmup_steps, gamma=cfg.gamma, lam=cfg.gae_lambda,
                             entropy=cfg.entropy_coef, clip_eps=cfg.clip_eps)
    return Learner(variant, game, env_params, dcfg, hp, init_dream, dream_step, "controller", controller_policy,
                   model_params, ("explore", "controller_on"))


def model_params(state):
    """The world model's parameters (the controller's included) of an online program's state."""
    if isinstance(state, DreamState):
        return state.model.params
    if isinstance(state, OnlineState):
        return state.train.params
    raise TypeError(f"{type(state).__name__} holds no world model")


def with_model_params(state, params):
    """An online program's `state` with the world model's parameters `params`."""
    if isinstance(state, DreamState):
        return state.replace(model=state.model.replace(params=params))
    if isinstance(state, OnlineState):
        return state.replace(train=state.train.replace(params=params))
    raise TypeError(f"{type(state).__name__} holds no world model")


def online_train_run(cfg: RunConfig, run: RunDir, resume: bool, progress: bool | None = None,
                     allow_data_change: bool = False, init_params=None) -> dict:
    """A controller variant, or PPO, trained against the game in `run`; ends with the policy
    table on stderr. `init_params`: the world model's parameters to start from (`--init-from`).
    (It plays the game: there is no data set to change, so `allow_data_change` has nothing to
    allow.)"""
    if not resume:
        cfg = with_obs_norm(cfg, run.data_cache)
    program = learner(cfg)
    state = program.fresh(cfg.seed)
    if init_params is not None:
        state = with_model_params(state, init_params)
    opened = run.open(cfg, state, resume)
    job = program.job(cfg, opened.checkpoints, opened.state)
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
            raise ValueError(f"run {run.path} trains the world model of {cfg.variant!r} offline (controller none), "
                             "so it has no controller to play with; train one from it with --init-from")
        raise ValueError(f"run {run.path} trains {cfg.variant!r}, which has no controller to play with")
    program = learner(cfg)
    state, _ = run.read_checkpoints().restore_newest(jax.eval_shape(lambda: program.fresh(cfg.seed)))
    return cfg, program, state


def eval_policy_run(run_dir: Path, episodes: int | None = None, seed: int = EVAL_SEED) -> dict[str, dict]:
    """`cdrl eval --policy RUN_DIR`: the run's learned policy (latest good checkpoint, no noise:
    a controller, or PPO's greedy policy) against the reference policies on the same held-out
    games."""
    check_episodes(episodes)
    run = RunDir(run_dir)
    cfg, program, state = restore_learner(run)
    return program.job(cfg, run.read_checkpoints(), state).play(state, episodes, seed)
