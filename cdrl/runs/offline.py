"""An offline training run: a variant trained on recorded episodes with truncated BPTT.

`offline_train_run(cfg, variant, run_dir, resume)` is what `cdrl train` runs for the
observation variants: the host loop over the jitted train step with metrics, periodic
held-out evaluation and checkpoints. A resumed run continues exactly where its last good
checkpoint left off: same state, same data cursor, so the same per-step losses.

With `devices` other than 1 the run is data parallel (`cdrl.training.parallel.DataParallel`):
the B streams are split over the devices, which may belong to several processes (`cdrl train
--distributed`). Every process then reads the whole chunk and places its devices' streams,
every process takes part in the checkpoints (global arrays; process 0 writes their metadata),
and process 0 alone writes the run's files (config, logs, evaluations, TensorBoard).
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import sys
import time

import jax
import numpy as np
from tqdm import tqdm

from cdrl.data.stream import ChunkStream
from cdrl.evaluation.metrics import evaluate
from cdrl.models import make_variant
from cdrl.runs.config import RunConfig
from cdrl.runs.distributed import is_primary, primary_first
from cdrl.runs.rundir import RunDir
from cdrl.runs.sources import load_episodes, verify_data, with_data_dims, with_obs_norm
from cdrl.runs.tboard import TBLog
from cdrl.training.loop import divergence_message, enter_stage, stage_schedule
from cdrl.training.parallel import DataParallel, local_copy
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
    parallel = DataParallel.create(cfg.devices, cfg.batch)
    writes = is_primary()

    def prepare():
        train_eps, test_eps = load_episodes(cfg, cache)
        verify_data(cfg, train_eps, test_eps)
        return train_eps, test_eps, cfg if resume else with_obs_norm(with_data_dims(cfg, train_eps), cache)

    train_eps, test_eps, cfg = primary_first(prepare, "loading the run's data")  # a game's data is collected once
    variant = make_variant(cfg.variant, cfg.arch)
    stream = ChunkStream(train_eps, cfg.batch, cfg.unroll, image_size=cfg.arch.image_size,
                         action_dim=cfg.arch.action_dim, seed=cfg.seed)
    hp = cfg.hparams(variant)
    key = jax.random.PRNGKey(cfg.seed)
    state = init_state(variant, key, cfg.batch, hp)
    if parallel is not None:
        state = parallel.place_state(state)
    opened = run.open(cfg, state, resume, write=writes)
    state, start, ckpts = opened.state, opened.start, opened.checkpoints
    if opened.meta is not None:
        stream.load_state_dict(opened.meta["stream"])

    names = ratio_names(state)
    schedule = stage_schedule(variant, cfg.steps)

    def stage(step: int, state, hp, resumed: bool = False):
        """`enter_stage`, with a fresh optimiser state placed on the devices like the old one."""
        staged, hp = enter_stage(variant, schedule, step, state, hp, resumed=resumed)
        if parallel is not None and staged is not state:
            staged = staged.replace(opt_state=parallel.place(staged.opt_state))
        return staged, hp

    state, hp = stage(start, state, hp, resumed=True)

    def meta(step):
        return {"step": step, "config": dataclasses.asdict(cfg), "stream": stream.state_dict(),
                "key": np.asarray(key).tolist()}

    if parallel is None:
        step_fn, host = functools.partial(train_step, variant), (lambda params: params)
    else:
        step_fn, host = parallel.step(variant, state), local_copy  # host: parameters for host-side work
    placed = {}  # the hyper-parameters on the devices, placed again when a stage changes them

    def inputs(hp, chunk):
        if parallel is None:
            return hp, chunk
        if placed.get("of") is not hp:
            placed.update({"of": hp, "hp": parallel.place(hp)})
        return placed["hp"], parallel.place_chunk(chunk)

    tb = TBLog(run.tb_dir, start, cfg.tensorboard and writes)
    if tb.replay_evals(run.evals.read(), start) and len(test_eps):
        tb.predictions(start, variant, host(state.params), test_eps[0])

    def run_eval(step, params):
        if not writes:
            return None
        params = host(params)
        episodes = [test_eps[i] for i in range(min(cfg.eval_episodes, len(test_eps)))]
        result = {"step": step, "split": "test", **evaluate(variant, params, episodes, cfg.unroll)}
        run.evals.append([result])
        tb.eval(result)
        tb.predictions(step, variant, params, episodes[0])
        tb.flush()
        return result

    show = (sys.stderr.isatty() if progress is None else progress) and writes
    bar = tqdm(total=cfg.steps, initial=start, disable=not show, desc=f"train {cfg.variant}", unit="step")
    log = run.metrics.append if writes else (lambda records: None)
    frames_per_step = cfg.batch * cfg.unroll
    pending, last_eval, t_last = [], None, time.perf_counter()
    with contextlib.closing(tb):
        for step in range(start, cfg.steps):
            if step > start:
                state, hp = stage(step, state, hp)
            state, metrics = step_fn(state, *inputs(hp, stream.next_chunk()))
            metrics = jax.device_get(metrics)
            now = time.perf_counter()
            fps, t_last = frames_per_step / max(now - t_last, 1e-9), now
            if metrics["diverged"]:
                message, group, ratio = divergence_message(step, metrics, names, cfg.diverge_threshold)
                log(pending)
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
                log(pending)
                pending = []
                ckpts.save(done, state, meta(done))
                tb.flush()
        log(pending)
        bar.close()
        if start < cfg.steps or last_eval is None:
            last_eval = run_eval(cfg.steps, state.params)
    return {"run_dir": str(run.path), "steps": cfg.steps, "final_eval": last_eval}
