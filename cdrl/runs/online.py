"""A training run of a controller variant against the built-in game (`cdrl train` runs it
for action_loop, reward_prediction and final_proposal).

The run directory has the layout of offline runs; `metrics.jsonl` lines add the real and
predicted reward, the finished episodes' returns, the exploration noise, and the excess ratio
of the chunk's next-frame predictions against copying the last frame (on the frames the
model is about to learn from, so before the update). Checkpoints hold
the whole `OnlineState` (games included), so a resumed run continues exactly.
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

from cdrl.evaluation.metrics import excess_ratio
from cdrl.evaluation.play import controller_policy, format_table, play, summarize
from cdrl.models import make_variant
from cdrl.models.base import Variant
from cdrl.runs.config import RunConfig
from cdrl.runs.rundir import RunDir
from cdrl.runs.sources import run_game, with_obs_norm
from cdrl.runs.tboard import TBLog
from cdrl.training.loop import divergence_message
from cdrl.training.monitor import group_names
from cdrl.training.online import OnlineConfig, OnlineHParams, init_online, online_step


def hparams(cfg: RunConfig) -> OnlineHParams:
    return OnlineHParams.create(opt=cfg.opt_hparams(), ascent=cfg.ascent, reward_weight=cfg.reward_weight,
                                noise_std=cfg.noise_std, noise_decay=cfg.noise_decay, warmup_steps=cfg.warmup_steps,
                                diverge_threshold=cfg.diverge_threshold, scope=cfg.scope)


def compare_policies(variant: Variant, params, game, env_params, episodes: int, max_steps: int,
                     seed: int = 10_000) -> dict[str, dict]:
    """The controller (no noise) against the thesis's two data policies, on the same seeds."""
    from envs.policies import get_policy

    seeds = np.arange(seed, seed + episodes)
    rows = {"controller": summarize(*play(game, env_params, *controller_policy(variant, params), seeds, max_steps))}
    for name in ("uniform", "behaviour"):
        policy = get_policy(name)
        rows[name] = summarize(*play(game, env_params, policy.init, policy.step, seeds, max_steps))
    return rows


def online_train_run(cfg: RunConfig, run: RunDir, resume: bool, progress: bool | None = None) -> dict:
    if not resume:
        cfg = with_obs_norm(cfg, run.path.parent / "data-cache")
    variant = make_variant(cfg.variant, cfg.arch)
    game, env_params = run_game(cfg)
    ocfg = OnlineConfig(num_envs=cfg.batch, unroll=cfg.unroll)
    hp = hparams(cfg)
    opened = run.open(cfg, init_online(variant, game, env_params, ocfg, jax.random.PRNGKey(cfg.seed), hp), resume)
    state, start, ckpts = opened.state, opened.start, opened.checkpoints
    names = group_names(state.train.params)
    tb = TBLog(run.tb_dir, start, cfg.tensorboard)
    tb.replay_evals(run.evals.read(), start)

    def evaluate_policies(step):
        rows = compare_policies(variant, state.train.params, game, env_params, cfg.eval_episodes, cfg.episode_steps)
        record = {"step": step, "split": "play", "policies": rows}
        run.evals.append([record])
        tb.eval(record)
        return rows

    show = sys.stderr.isatty() if progress is None else progress
    bar = tqdm(total=cfg.steps, initial=start, disable=not show, desc=f"online {cfg.variant}", unit="step")
    pending, rows, t_last = [], None, time.perf_counter()
    for step in range(start, cfg.steps):
        state, m = online_step(variant, game, ocfg, state, hp, env_params)
        m = jax.device_get(m)
        now = time.perf_counter()
        fps, t_last = cfg.batch * cfg.unroll / max(now - t_last, 1e-9), now
        if m["diverged"]:
            message, _, _ = divergence_message(step, m, names, cfg.diverge_threshold)
            run.metrics.append(pending)
            ckpts.save(step, state, {"step": step, "config": dataclasses.asdict(cfg)})
            bar.close()
            raise RuntimeError(message + f" Last good state saved in {ckpts.directory / str(step)}.")
        episodes = int(m["episodes"])
        terms = {k: float(v) for k, v in m["terms"].items()}
        pending.append({
            "step": step, "loss": float(m["loss"]), "terms": terms,
            "excess_ratio": excess_ratio(terms["obs_bce"], terms["copy_bce"], terms["target_entropy"]),
            "reward": float(m["reward"]), "episodes": episodes,
            "mean_return": float(m["return_sum"]) / episodes if episodes else None,
            "action_mean": np.asarray(m["action_mean"]).tolist(), "noise_std": float(m["noise_std"]),
            "ascent_on": bool(m["ascent_on"]), "max_ratio": float(m["max_ratio"]),
            "worst_group": names[int(m["worst_group"])],
            "ratios": dict(zip(names, np.asarray(m["ratios"]).tolist())), "fps": fps,
        })
        tb.step(pending[-1])
        bar.update(1)
        bar.set_postfix(loss=f"{pending[-1]['loss']:.4f}", reward=f"{pending[-1]['reward']:.3f}")
        done = step + 1
        if cfg.eval_every and done % cfg.eval_every == 0 and done < cfg.steps:
            rows = evaluate_policies(done)
        if done % cfg.checkpoint_every == 0 or done == cfg.steps:
            run.metrics.append(pending)
            pending = []
            ckpts.save(done, state, {"step": done, "config": dataclasses.asdict(cfg)})
            tb.flush()
    run.metrics.append(pending)
    bar.close()
    if start < cfg.steps or rows is None:
        rows = evaluate_policies(cfg.steps)
    tb.close()
    print(format_table(rows), file=sys.stderr)
    return {"run_dir": str(run.path), "steps": cfg.steps, "policies": rows}


def eval_policy_run(run_dir: Path, episodes: int | None = None, seed: int = 10_000) -> dict[str, dict]:
    """`cdrl eval --policy RUN_DIR`: the run's controller (latest good checkpoint, no noise)
    against the uniform-random and behaviour-switching policies on the same held-out seeds."""
    run = RunDir(run_dir)
    cfg = run.read_config()
    variant = make_variant(cfg.variant, cfg.arch)
    if not variant.has_controller:
        raise ValueError(f"run {run.path} trains {cfg.variant!r}, which has no controller to play with")
    game, env_params = run_game(cfg)
    like = jax.eval_shape(lambda: init_online(variant, game, env_params, OnlineConfig(cfg.batch, cfg.unroll),
                                              jax.random.PRNGKey(cfg.seed), hparams(cfg)))
    state, _, warnings = run.read_checkpoints().restore_latest_good(like)
    for w in warnings:
        print(f"warning: {w}; using an older checkpoint", file=sys.stderr)
    return compare_policies(variant, state.train.params, game, env_params, episodes or cfg.eval_episodes,
                            cfg.episode_steps, seed)
