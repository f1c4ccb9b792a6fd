"""An offline training run: a variant trained on recorded episodes with truncated BPTT.

`offline_train_run(cfg, variant, run_dir, resume)` is what `cdrl train` runs for the
observation variants: the host loop over the jitted train step with metrics, periodic
held-out evaluation and checkpoints. A resumed run continues exactly where its last good
checkpoint left off: same state, same data cursor, so the same per-step losses.
"""
from __future__ import annotations

import contextlib
import dataclasses
import sys
import time

import jax
import numpy as np
from tqdm import tqdm

from cdrl.data.stream import ChunkStream
from cdrl.evaluation.metrics import evaluate
from cdrl.models import make_variant
from cdrl.runs.config import RunConfig
from cdrl.runs.rundir import RunDir
from cdrl.runs.sources import load_episodes, verify_data, with_data_dims, with_obs_norm
from cdrl.runs.tboard import TBLog
from cdrl.training.loop import divergence_message, enter_stage, stage_schedule
from cdrl.training.step import init_state, ratio_names, train_step


def step_record(step: int, metrics: dict, names: list[str], fps: float) -> dict:
    """The `metrics.jsonl` record of one step from its (host) metrics."""
    return {
        "step": step,
        "loss": float(metrics["loss"]),
        "terms": {k: float(v) for k, v in metrics["terms"].items()},
        "max_ratio": float(metrics["max_ratio"]),
        "worst_group": names[int(metrics["worst_group"])],
        "ratios": dict(zip(names, np.asarray(metrics["ratios"]).tolist())),
        "fps": fps,
    }


def offline_train_run(cfg: RunConfig, run: RunDir, resume: bool, progress: bool | None = None) -> dict:
    cache = run.path.parent / "data-cache"
    train_eps, test_eps = load_episodes(cfg, cache)
    verify_data(cfg, train_eps, test_eps)
    if not resume:
        cfg = with_obs_norm(with_data_dims(cfg, train_eps), cache)
    variant = make_variant(cfg.variant, cfg.arch)
    stream = ChunkStream(train_eps, cfg.batch, cfg.unroll, image_size=cfg.arch.image_size,
                         action_dim=cfg.arch.action_dim, seed=cfg.seed)
    hp = cfg.hparams(variant)
    key = jax.random.PRNGKey(cfg.seed)
    opened = run.open(cfg, init_state(variant, key, cfg.batch, hp), resume)
    state, start, ckpts = opened.state, opened.start, opened.checkpoints
    if opened.meta is not None:
        stream.load_state_dict(opened.meta["stream"])

    names = ratio_names(state)
    schedule = stage_schedule(variant, cfg.steps)
    state, hp = enter_stage(variant, schedule, start, state, hp, resumed=True)

    def meta(step):
        return {"step": step, "config": dataclasses.asdict(cfg), "stream": stream.state_dict(),
                "key": np.asarray(key).tolist()}

    tb = TBLog(run.tb_dir, start, cfg.tensorboard)
    if tb.replay_evals(run.evals.read(), start) and len(test_eps):
        tb.predictions(start, variant, state.params, test_eps[0])

    def run_eval(step, params):
        episodes = [test_eps[i] for i in range(min(cfg.eval_episodes, len(test_eps)))]
        result = {"step": step, "split": "test", **evaluate(variant, params, episodes, cfg.unroll)}
        run.evals.append([result])
        tb.eval(result)
        tb.predictions(step, variant, params, episodes[0])
        tb.flush()
        return result

    show = sys.stderr.isatty() if progress is None else progress
    bar = tqdm(total=cfg.steps, initial=start, disable=not show, desc=f"train {cfg.variant}", unit="step")
    frames_per_step = cfg.batch * cfg.unroll
    pending, last_eval, t_last = [], None, time.perf_counter()
    with contextlib.closing(tb):
        for step in range(start, cfg.steps):
            if step > start:
                state, hp = enter_stage(variant, schedule, step, state, hp)
            state, metrics = train_step(variant, state, hp, stream.next_chunk())
            metrics = jax.device_get(metrics)
            now = time.perf_counter()
            fps, t_last = frames_per_step / max(now - t_last, 1e-9), now
            if metrics["diverged"]:
                message, group, ratio = divergence_message(step, metrics, names, cfg.diverge_threshold)
                run.metrics.append(pending)
                ckpts.save(step, state, meta(step))
                bar.close()
                raise RuntimeError(message + f" Last good state saved in {ckpts.directory / str(step)}.")
            pending.append(step_record(step, metrics, names, fps))
            tb.step(pending[-1])
            bar.update(1)
            bar.set_postfix(loss=f"{pending[-1]['loss']:.4f}", fps=f"{fps:.0f}")
            done = step + 1
            if cfg.eval_every and done % cfg.eval_every == 0 and done < cfg.steps:
                last_eval = run_eval(done, state.params)
            if done % cfg.checkpoint_every == 0 or done == cfg.steps:
                run.metrics.append(pending)
                pending = []
                ckpts.save(done, state, meta(done))
                tb.flush()
        run.metrics.append(pending)
        bar.close()
        if start < cfg.steps or last_eval is None:
            last_eval = run_eval(cfg.steps, state.params)
    return {"run_dir": str(run.path), "steps": cfg.steps, "final_eval": last_eval}
