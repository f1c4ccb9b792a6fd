"""A training run: config, data, the host loop with metrics, evaluation and checkpoints.

A run directory holds `config.json` (the full resolved config), `metrics.jsonl` (one line
per step: loss, loss terms, every group's norm ratio, frames/s), `eval.jsonl` (periodic
held-out evaluation), `checkpoints/` (orbax) and `plots/`. `train_run(cfg, run_dir)`
starts a run; `train_run(None, run_dir, resume=True)` continues it exactly where its last
good checkpoint left off: same state, same data cursor, so the same per-step losses.
"""
from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

from cdrl import config as configs
from cdrl import data as data_lib
from cdrl.checkpoint import CheckpointError, Checkpoints
from cdrl.evaluate import evaluate
from cdrl.loop import divergence_message, enter_stage, stage_schedule
from cdrl.train import HParams, init_state, ratio_names, train_step
from cdrl.variants import make_variant


def _opt(default, help: str):
    return dataclasses.field(default=default, metadata={"help": help})


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Everything that defines a training run (the CLI's `train` options map onto it)."""

    variant: str = _opt("main", "model variant (see `cdrl variants`)")
    preset: str = _opt("small", "architecture preset: thesis (150x150, LSTM 512), small (64x64) or tiny")
    data: str = _opt("game", "'game' (collect from the built-in game and cache it), 'synthetic', or a data set directory")
    episodes: int = _opt(60, "episodes to collect when data is 'game' or 'synthetic'")
    episode_steps: int = _opt(200, "step limit of a collected episode")
    unroll: int = _opt(32, "truncated-BPTT length T")
    batch: int = _opt(1, "independent episode streams per step B")
    lr: float = _opt(0.1, "SGD learning rate")
    momentum: float = _opt(0.9, "SGD momentum")
    steps: int = _opt(1000, "training steps (chunks)")
    seed: int = _opt(0, "seed of the parameters and the data order")
    diverge_threshold: float = _opt(1e3, "a norm ratio ||grad||/||param|| above this stops the run")
    checkpoint_every: int = _opt(200, "steps between checkpoints")
    keep_checkpoints: int = _opt(3, "how many checkpoints to keep")
    eval_every: int = _opt(250, "steps between held-out evaluations (0: only at the end)")
    eval_episodes: int = _opt(4, "held-out episodes per evaluation (online variants: games per policy)")
    env: str = _opt("", "game parameters for the built-in game, e.g. 'max_steps=300,left_bonus=1'")
    scope: str = _opt("controller", "online variants: parameters the reward ascent may change: controller or all")
    ascent: float = _opt(0.1, "online variants: lambda, the weight of the predicted-reward ascent term")
    reward_weight: float = _opt(0.1, "online variants: weight of the reward-prediction loss (SGD lr 0.1 with momentum 0.9 oscillates on it at 1)")
    noise_std: float = _opt(0.3, "online variants: std of the exploration noise on the controller's actions")
    noise_decay: float = _opt(0.999, "online variants: per-update decay factor of the exploration noise")
    warmup_steps: int = _opt(100, "online variants: updates of pure model learning before the ascent term")

    def __post_init__(self):
        configs.preset(self.preset)
        for name in ("unroll", "batch", "steps", "episodes", "episode_steps", "checkpoint_every", "keep_checkpoints"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.scope not in ("controller", "all"):
            raise ValueError(f"scope must be 'controller' or 'all', got {self.scope!r}")
        if self.lr <= 0 or not 0 <= self.momentum < 1:
            raise ValueError(f"need lr > 0 and 0 <= momentum < 1, got lr={self.lr}, momentum={self.momentum}")

    @property
    def arch(self) -> configs.ArchConfig:
        return configs.preset(self.preset)


# Options that may change when a run is resumed (they do not change what the steps compute).
RESUMABLE = {"steps", "checkpoint_every", "keep_checkpoints", "eval_every", "eval_episodes"}


def atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def load_episodes(cfg: RunConfig, cache_root: Path):
    """(train, test) episode sources for the run."""
    size = cfg.arch.image_size
    if cfg.data == "synthetic":
        n_test = max(1, cfg.episodes // 10)
        pushed = make_variant(cfg.variant, cfg.arch).uses_action
        train = data_lib.synthetic_episodes(cfg.episodes - n_test, cfg.episode_steps, size, cfg.seed, pushed=pushed)
        test = data_lib.synthetic_episodes(n_test, cfg.episode_steps, size, cfg.seed + 10_000, pushed=pushed)
        return train, test
    from cdrl import dataset

    if cfg.data == "game":
        policy = "uniform" if make_variant(cfg.variant, cfg.arch).uses_action else "behaviour"
        path = cache_root / f"slither-{policy}-{size}px-{cfg.episodes}ep-{cfg.episode_steps}steps-seed{cfg.seed}"
        dataset.collect(path, cfg.episodes, policy=policy, seed=cfg.seed, max_steps=cfg.episode_steps, obs_size=size)
    else:
        path = Path(cfg.data)
    return dataset.EpisodeDataset(path, split="train"), dataset.EpisodeDataset(path, split="test")


class RunLog:
    """Append-only JSON-lines files of a run, cut back to a step on resume."""

    def __init__(self, path: Path):
        self.path = path

    def truncate(self, before_step: int) -> None:
        if not self.path.exists():
            return
        keep = [line for line in self.path.read_text().splitlines() if line and json.loads(line)["step"] < before_step]
        atomic_write_text(self.path, "".join(line + "\n" for line in keep))

    def append(self, records: list[dict]) -> None:
        with open(self.path, "a") as f:
            for record in records:
                f.write(json.dumps(record) + "\n")


def _check_compatible(cfg: RunConfig):
    def check(meta):
        saved = meta.get("config", {})
        diffs = [
            f"{k}: checkpoint has {saved.get(k)!r}, run has {v!r}"
            for k, v in dataclasses.asdict(cfg).items()
            if k not in RESUMABLE and saved.get(k) != v
        ]
        if diffs:
            raise CheckpointError("the checkpoint comes from an incompatible config: " + "; ".join(diffs))

    return check


def open_run(cfg: RunConfig, run_dir: Path, state, resume: bool):
    """The checkpoints and logs of a run; when resuming, `state` restored from the last good
    checkpoint (an older one if the newest is corrupt) and the logs cut back to it. Writes the
    run's config. Returns (state, checkpoint meta or None, first step, checkpoints, metrics log,
    eval log)."""
    ckpts = Checkpoints(run_dir / "checkpoints", keep=cfg.keep_checkpoints)
    metrics_log, eval_log = RunLog(run_dir / "metrics.jsonl"), RunLog(run_dir / "eval.jsonl")
    start, meta = 0, None
    if resume and ckpts.steps():
        state, meta, warnings = ckpts.restore_latest_good(state, check_meta=_check_compatible(cfg))
        for w in warnings:
            print(f"warning: {w}; using an older checkpoint", file=sys.stderr)
        start = int(meta["step"])
    atomic_write_text(run_dir / "config.json", json.dumps(dataclasses.asdict(cfg), indent=2) + "\n")
    metrics_log.truncate(start)
    eval_log.truncate(start + 1)
    return state, meta, start, ckpts, metrics_log, eval_log


def train_run(cfg: RunConfig | None, run_dir: str | Path, resume: bool = False, overrides: dict | None = None,
              progress: bool | None = None) -> dict:
    """Train (or resume) a run in `run_dir`; returns a summary dict. Raises `DivergenceError`-like
    `RuntimeError`s with a clear message when the run diverges (the last good state is saved)."""
    run_dir = Path(run_dir)
    config_path = run_dir / "config.json"
    if resume:
        if not config_path.exists():
            raise FileNotFoundError(f"cannot resume: {config_path} does not exist")
        saved = json.loads(config_path.read_text())
        cfg = RunConfig(**{**saved, **(overrides or {})})
    elif cfg is None:
        raise ValueError("train_run needs a config unless resuming")
    elif config_path.exists():
        raise FileExistsError(f"{run_dir} already holds a run; use --resume to continue it or pick another --run-dir")
    run_dir.mkdir(parents=True, exist_ok=True)

    variant = make_variant(cfg.variant, cfg.arch)
    if variant.has_controller:
        from cdrl.online_run import online_train_run

        return online_train_run(cfg, variant, run_dir, resume, progress)
    train_eps, test_eps = load_episodes(cfg, run_dir.parent / "data-cache")
    stream = data_lib.ChunkStream(train_eps, cfg.batch, cfg.unroll, image_size=cfg.arch.image_size, seed=cfg.seed)
    hp = HParams.create(variant, cfg.lr, cfg.momentum, diverge_threshold=cfg.diverge_threshold)
    key = jax.random.PRNGKey(cfg.seed)
    state = init_state(variant, key, cfg.batch, hp)
    state, meta, start, ckpts, metrics_log, eval_log = open_run(cfg, run_dir, state, resume)
    if meta is not None:
        stream.load_state_dict(meta["stream"])

    names = ratio_names(state)
    schedule = stage_schedule(variant, cfg.steps)
    state, hp = enter_stage(variant, schedule, start, state, hp, resumed=True)

    def meta(step):
        return {"step": step, "config": dataclasses.asdict(cfg), "stream": stream.state_dict(),
                "key": np.asarray(key).tolist()}

    def run_eval(step, params):
        episodes = [test_eps[i] for i in range(min(cfg.eval_episodes, len(test_eps)))]
        result = {"step": step, "split": "test", **evaluate(variant, params, episodes, cfg.unroll)}
        eval_log.append([result])
        return result

    show = sys.stderr.isatty() if progress is None else progress
    bar = tqdm(total=cfg.steps, initial=start, disable=not show, desc=f"train {cfg.variant}", unit="step")
    frames_per_step = cfg.batch * cfg.unroll
    pending, last_eval, t_last = [], None, time.perf_counter()
    for step in range(start, cfg.steps):
        if step > start:
            state, hp = enter_stage(variant, schedule, step, state, hp)
        state, metrics = train_step(variant, state, hp, stream.next_chunk())
        metrics = jax.device_get(metrics)
        now = time.perf_counter()
        fps, t_last = frames_per_step / max(now - t_last, 1e-9), now
        if metrics["diverged"]:
            message, group, ratio = divergence_message(step, metrics, names, cfg.diverge_threshold)
            metrics_log.append(pending)
            ckpts.save(step, state, meta(step))
            bar.close()
            raise RuntimeError(message + f" Last good state saved in {ckpts.directory / str(step)}.")
        pending.append({
            "step": step,
            "loss": float(metrics["loss"]),
            "terms": {k: float(v) for k, v in metrics["terms"].items()},
            "max_ratio": float(metrics["max_ratio"]),
            "worst_group": names[int(metrics["worst_group"])],
            "ratios": dict(zip(names, np.asarray(metrics["ratios"]).tolist())),
            "fps": fps,
        })
        bar.update(1)
        bar.set_postfix(loss=f"{pending[-1]['loss']:.4f}", fps=f"{fps:.0f}")
        done = step + 1
        if cfg.eval_every and done % cfg.eval_every == 0 and done < cfg.steps:
            last_eval = run_eval(done, state.params)
        if done % cfg.checkpoint_every == 0 or done == cfg.steps:
            metrics_log.append(pending)
            pending = []
            ckpts.save(done, state, meta(done))
    metrics_log.append(pending)
    bar.close()
    if start < cfg.steps or last_eval is None:
        last_eval = run_eval(cfg.steps, state.params)
    return {"run_dir": str(run_dir), "steps": cfg.steps, "final_eval": last_eval}
