"""An offline training run: a variant trained on recorded episodes with truncated BPTT.

`offline_train_run(cfg, run_dir, resume)` is what `cdrl train` runs for the observation
variants: the host loop (`cdrl.training.loop.host_loop`) over the jitted train step
(`OfflineJob`), with periodic held-out evaluation and checkpoints. A resumed run continues
exactly where its last good checkpoint left off: same state, same data cursor, so the same
per-step losses.

With `devices` other than 1 the run is data parallel (`cdrl.training.parallel.DataParallel`):
the B streams are split over the devices, which may belong to several processes (`cdrl train
--distributed`). Every process then reads the whole chunk and places its devices' streams,
every process takes part in the checkpoints (global arrays; process 0 writes their metadata),
and process 0 alone writes the run's files (config, logs, evaluations, TensorBoard).
"""
from __future__ import annotations

import contextlib
import dataclasses
import sys

import jax
import numpy as np

from cdrl.data.fingerprint import fingerprint
from cdrl.data.stream import ChunkStream
from cdrl.evaluation.metrics import evaluate
from cdrl.models import make_variant
from cdrl.runs.checkpoint import Checkpoints
from cdrl.runs.config import RunConfig
from cdrl.runs.distributed import is_primary, primary_first
from cdrl.runs.rundir import RunDir
from cdrl.runs.sources import load_episodes, step_limit, verify_data, with_data_dims, with_obs_norm
from cdrl.runs.tboard import prediction_image
from cdrl.runs.record_sinks import run_writer
from cdrl.training.loop import Plan, TrainJob, host_loop
from cdrl.training.parallel import DataParallel, local_copy
from cdrl.training.step import init_state, ratio_names


class OfflineJob(TrainJob):
    """`TrainJob` with the run's held-out evaluation, its checkpoints (state, data cursor,
    key) and, on several devices, the data-parallel layout."""

    def __init__(self, cfg: RunConfig, variant, stream: ChunkStream, test_eps, state, ckpts: Checkpoints,
                 parallel: DataParallel | None, writes: bool):
        super().__init__(variant, stream, cfg.hparams(variant), cfg.steps, ratio_names(state),
                         curriculum=cfg.feed_curriculum)
        self.cfg, self.test_eps, self.ckpts, self.parallel, self.writes = cfg, test_eps, ckpts, parallel, writes
        self.key = jax.random.PRNGKey(cfg.seed)
        self.threshold = cfg.diverge_threshold
        self._placed = {}  # the hyper-parameters on the devices, placed again when a stage changes them
        if parallel is not None:
            self.run_step = parallel.step(variant, state)

    def host_params(self, params):
        """Parameters for host-side work (evaluation): one device's copy of replicated ones."""
        return params if self.parallel is None else local_copy(params)

    def stage(self, step: int, state, resumed: bool):
        staged = super().stage(step, state, resumed)
        if self.parallel is not None and staged is not state:
            staged = staged.replace(opt_state=self.parallel.place(staged.opt_state))
        return staged

    def inputs(self, chunk):
        if self.parallel is None:
            return self.hp, chunk
        if self._placed.get("of") is not self.hp:
            self._placed = {"of": self.hp, "hp": self.parallel.place(self.hp)}
        return self._placed["hp"], self.parallel.place_chunk(chunk)

    def held_out(self) -> list:
        return [self.test_eps[i] for i in range(min(self.cfg.eval_episodes, len(self.test_eps)))]

    def evaluate(self, step, state, lanes):
        if not self.writes or not lanes:
            return {}
        params = self.host_params(state.params)
        episodes = self.held_out()
        record = {"step": step, "split": "test", **evaluate(self.variant, params, episodes, self.cfg.unroll)}
        return {0: (record, prediction_image(self.variant, params, episodes[0]))}

    def meta(self, step: int) -> dict:
        return {"step": step, "config": dataclasses.asdict(self.cfg), "stream": self.stream.state_dict(),
                "key": np.asarray(self.key).tolist()}

    def save(self, step, state, saves, alive, diverged):
        self.ckpts.save(step, state, self.meta(step))
        return str(self.ckpts.directory / str(step))


def offline_train_run(cfg: RunConfig, run: RunDir, resume: bool, progress: bool | None = None,
                      allow_data_change: bool = False, init_params=None) -> dict:
    """Train (or resume) the offline run of `cfg` in `run`, from the parameters `init_params`
    if given (`--init-from`). Its data is checked, and on a resume compared with the
    fingerprint the run recorded (`RunDir.check_data`), before anything is written."""
    parallel = DataParallel.create(cfg.devices, cfg.batch)
    writes = is_primary()

    def prepare():
        train_eps, test_eps = load_episodes(cfg, run.data_cache)
        verify_data(cfg, train_eps, test_eps)
        data = fingerprint(train_eps, test_eps)
        return (train_eps, test_eps, data,
                cfg if resume else with_obs_norm(with_data_dims(cfg, train_eps), run.data_cache))

    # a game's data is collected once
    train_eps, test_eps, data, cfg = primary_first(prepare, "loading the run's data")
    variant = make_variant(cfg.variant, cfg.arch)
    stream = ChunkStream(train_eps, cfg.batch, cfg.unroll, image_size=cfg.arch.image_size,
                         action_dim=cfg.arch.action_dim, seed=cfg.seed, step_limit=step_limit(train_eps))
    state = init_state(variant, jax.random.PRNGKey(cfg.seed), cfg.batch, cfg.hparams(variant))
    if init_params is not None:
        state = state.replace(params=init_params)
    if parallel is not None:
        state = parallel.place_state(state)
    opened = run.open(cfg, state, resume, write=writes, data=data, allow_data_change=allow_data_change)
    if opened.meta is not None:
        stream.load_state_dict(opened.meta["stream"])
    job = OfflineJob(cfg, variant, stream, test_eps, opened.state, opened.checkpoints, parallel, writes)
    sink = run_writer(run, opened.start, cfg.tensorboard, writes)
    if writes and sink.replayed and len(test_eps):  # the purged image of the step it resumes at
        sink.image(opened.start, prediction_image(variant, job.host_params(opened.state.params), test_eps[0]))
    plan = Plan(steps=cfg.steps, start=opened.start, eval_every=cfg.eval_every, checkpoint_every=cfg.checkpoint_every)
    show = (sys.stderr.isatty() if progress is None else progress) and writes
    with contextlib.closing(sink):
        result = host_loop(job, opened.state, plan, [sink], progress=show)
        final = result.last_eval.get(0)
        if final is None and writes:  # a finished run resumed: its final evaluation, made now if it is missing
            final = next((r for r in reversed(run.evals.read()) if r["step"] == cfg.steps), None)
            if final is None:
                final, image = job.evaluate(cfg.steps, result.state, [0])[0]
                sink.evaluation(final, image)
    return {"run_dir": str(run.path), "steps": cfg.steps, "final_eval": final}
