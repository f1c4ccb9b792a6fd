"""Time to quality: seconds and training frames until `main` predicts held-out frames of the
built-in game better than copying the last one.

The figure of merit is the held-out excess ratio (BCE - entropy floor) / (copy-last BCE -
entropy floor) on fixed held-out frames (the first `--eval-episodes` episodes of the test split, all by default): below
1 the model beats copying the last frame. Each row trains from the same initial weights on
the same chunks and evaluates every `--eval-every` steps, and once past 20 of those, every
5 % of the steps done (so the time of a crossing is known to 5 % while evaluations, which
score every held-out frame, stay a small part of a long row); it reports the training seconds
(wall clock of the train steps, the first step's compilation included and also given
apart; evaluations excluded) and frames at which the ratio first falls below 1.0 and below
0.5, or "not reached" and the ratio at the row's budget cap.

Rows (`--rows`, any subset, run one after another in this process):
  small-thesis       small preset, the thesis's recipe (SGD lr 0.1, momentum 0.9, B 1, raw input)
  small-fast         small preset, the `fast` recipe (cdrl's best)
  small-fast-warm    small-fast in a new process whose train step is already in JAX's persistent
                     compilation cache (`--compile-cache DIR`, default a fresh temporary one, filled
                     first by another process): what a second run of the same configuration
                     pays, as `cdrl train` with its cache does
  small-fast-torch   the same recipe, weights and chunks in the eager PyTorch reference
                     (reference/torch_model.py), evaluated by cdrl's evaluation
  small-fast-onednn  small-fast with oneDNN's convolutions (`--conv onednn`); run it after the
                     torch row: PyTorch shares oneDNN's OpenMP runtime, whose teams started from
                     XLA's threads slow PyTorch's for the rest of the process
  thesis-fast        thesis preset (150 x 150, LSTM 512), the `fast` recipe

    .venv/bin/python experiments/learning/time_to_quality.py --rows small-fast small-fast-torch --cap 600
    .venv/bin/python experiments/learning/time_to_quality.py --rows small-fast small-fast-warm small-fast-torch \
        --cap 60                                                # to 1: cold, warm, PyTorch
    .venv/bin/python experiments/learning/time_to_quality.py --quick     # seconds: does it run?

One JSON line at the end; `--out FILE` also writes it to FILE.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from cdrl.data.stream import ChunkStream
from cdrl.evaluation.metrics import evaluate
from cdrl.models import make_variant
from cdrl.runs import compile_cache
from cdrl.runs.config import RunConfig
from cdrl.runs.sources import load_episodes, with_obs_norm
from cdrl.training.step import init_state, train_step

if not __package__:  # run as a file, not with -m: the repository root on the path (benchmarks/, experiments/)
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import emit, warn_if_busy  # noqa: E402

ROWS = {
    "small-thesis": dict(preset="small", recipe="thesis", framework="cdrl"),
    "small-fast": dict(preset="small", recipe="fast", framework="cdrl"),
    "small-fast-warm": dict(preset="small", recipe="fast", framework="cdrl", compile_cache="warm"),
    "small-fast-torch": dict(preset="small", recipe="fast", framework="torch"),
    "small-fast-onednn": dict(preset="small", recipe="fast", framework="cdrl", conv="onednn"),
    "thesis-fast": dict(preset="thesis", recipe="fast", framework="cdrl"),
}
TARGETS = (1.0, 0.5)


def _parse(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS), help="rows to run, in order")
    p.add_argument("--cap", type=float, default=1800.0, help="training seconds per row at most (default: 1800)")
    p.add_argument("--caps", nargs="+", default=[], metavar="ROW=SECONDS", help="per-row caps, e.g. thesis-fast=3600")
    p.add_argument("--episodes", type=int, default=60, help="episodes of the data set (default: 60)")
    p.add_argument("--episode-steps", type=int, default=200, help="step limit of an episode (default: 200)")
    p.add_argument("--level", default="thesis", help="game level (default: thesis)")
    p.add_argument("--eval-every", type=int, default=0,
                   help="steps between the first 20 evaluations, then 5 %% of the steps done "
                        "(default: 50 for the small preset, 100 for thesis)")
    p.add_argument("--eval-episodes", type=int, default=0,
                   help="held-out episodes scored, the first N of the test split (default: all)")
    p.add_argument("--seed", type=int, default=0, help="seed of the data set, the weights and the data order")
    p.add_argument("--cache", default="runs/data-cache", help="data set cache (default: runs/data-cache)")
    p.add_argument("--torch-threads", type=int, default=0, help="torch threads (default: all cores)")
    p.add_argument("--quick", action="store_true", help="tiny caps and few episodes: a smoke run")
    p.add_argument("--compile-cache", default=None, metavar="DIR",
                   help="JAX's persistent compilation cache of this process, and of the small-fast-warm row's "
                        "processes (default: none in this process; a fresh temporary one for that row)")
    p.add_argument("--prime", action="store_true",
                   help="only compile each row's train step (one step) into --compile-cache, then exit")
    p.add_argument("--out", default=None, help="also write the JSON line to this file")
    return p.parse_args(argv)


def _config(row: dict, args) -> RunConfig:
    cfg = RunConfig(variant="main", preset=row["preset"], recipe=row["recipe"], level=args.level,
                    episodes=args.episodes, episode_steps=args.episode_steps, seed=args.seed,
                    steps=1_000_000, conv=row.get("conv", "auto"))
    return with_obs_norm(cfg, Path(args.cache))


class _Cdrl:
    """cdrl's jitted train step on a `TrainState`."""

    def __init__(self, cfg: RunConfig, variant, params):
        self.variant, self.hp = variant, cfg.hparams(variant)
        self.state = init_state(variant, jax.random.PRNGKey(cfg.seed), cfg.batch, self.hp)
        self.state = self.state.replace(params=jax.tree.map(jnp.array, params))  # copied: the step donates

    def step(self, chunk) -> float:
        self.state, metrics = train_step(self.variant, self.state, self.hp, chunk)
        return float(metrics["loss"])  # waits for the step

    def params(self):
        return self.state.params


class _Torch:
    """The eager PyTorch reference, SGD with momentum, the recipe's schedule."""

    def __init__(self, cfg: RunConfig, variant, params):
        import torch

        from reference import torch_model as tr

        if cfg.optimizer != "sgd" or cfg.grad_clip:
            raise ValueError("the torch reference trains with SGD and no clipping only")
        self.torch, self.tr = torch, tr
        self.model = tr.load_cdrl_params(tr.TorchModel(variant.arch, "main"), params)
        self.opt = tr.make_optimizer(self.model, lr=cfg.lr, momentum=cfg.momentum)
        opt = cfg.opt_hparams()
        factor = lambda count: float(opt.learning_rate(np.int32(count))) / cfg.lr  # noqa: E731
        self.sched = torch.optim.lr_scheduler.LambdaLR(self.opt, factor)
        self.carry = self.model.init_carry(cfg.batch)

    def step(self, chunk) -> float:
        t = self.torch.from_numpy
        loss, self.carry, _ = self.tr.train_step(self.model, self.opt, self.carry, t(np.asarray(chunk.obs)),
                                                 t(np.asarray(chunk.next_obs)), t(np.asarray(chunk.is_first)),
                                                 monitor=True)
        self.sched.step()
        return float(loss)

    def params(self):
        return jax.tree.map(np.asarray, self.tr.params_as_cdrl(self.model))


def run_warm_row(name: str, args, cap: float) -> dict:
    """`name`'s cdrl row in a new process after another process compiled its train step into the
    persistent cache: the row's compile seconds are then a cache read."""
    import subprocess
    import tempfile

    base = name.removesuffix("-warm")
    cache = args.compile_cache or tempfile.mkdtemp(prefix="cdrl-ttq-cache-")
    common_args = [sys.executable, str(Path(__file__).resolve()), "--rows", base, "--compile-cache", cache,
                   "--episodes", str(args.episodes), "--episode-steps", str(args.episode_steps), "--level", args.level,
                   "--eval-every", str(args.eval_every), "--eval-episodes", str(args.eval_episodes),
                   "--seed", str(args.seed), "--cache", args.cache, "--caps", f"{base}={cap}"]
    subprocess.run(common_args + ["--prime"], check=True)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "row.json"
        subprocess.run(common_args + ["--out", str(out)], check=True)
        row = json.loads(out.read_text())["rows"][0]
    return {**row, "row": name, "compile_cache": cache}


def prime_row(name: str, args) -> None:
    """One train step of `name`'s cdrl row: its program compiled into the persistent cache."""
    cfg = _config(ROWS[name], args)
    train_eps, _ = load_episodes(cfg, Path(args.cache))
    variant = make_variant(cfg.variant, cfg.arch)
    trainer = _Cdrl(cfg, variant, variant.init(jax.random.PRNGKey(cfg.seed)))
    trainer.step(ChunkStream(train_eps, cfg.batch, cfg.unroll, image_size=cfg.arch.image_size, seed=cfg.seed).next_chunk())


def run_row(name: str, args, cap: float) -> dict:
    spec = ROWS[name]
    if spec.get("compile_cache") == "warm":
        return run_warm_row(name, args, cap)
    cfg = _config(spec, args)
    cache = Path(args.cache)
    train_eps, test_eps = load_episodes(cfg, cache)
    n_eval = min(args.eval_episodes or len(test_eps), len(test_eps))
    held_out = [test_eps[i] for i in range(n_eval)]
    variant = make_variant(cfg.variant, cfg.arch)
    params = variant.init(jax.random.PRNGKey(cfg.seed))
    trainer = (_Torch if spec["framework"] == "torch" else _Cdrl)(cfg, variant, params)
    stream = ChunkStream(train_eps, cfg.batch, cfg.unroll, image_size=cfg.arch.image_size, seed=cfg.seed)
    eval_every = args.eval_every or (100 if cfg.preset == "thesis" else 50)
    frames_per_step = cfg.batch * cfg.unroll

    def ratio_now() -> dict:
        t0 = time.perf_counter()
        scores = evaluate(variant, trainer.params(), held_out, cfg.unroll)
        return {"ratio": scores["excess_ratio"], "bce": scores["bce"], "eval_seconds": time.perf_counter() - t0}

    first = ratio_now()
    row = {"row": name, **spec, "level": cfg.level, "lr": cfg.lr, "momentum": cfg.momentum, "batch": cfg.batch,
           "unroll": cfg.unroll, "optimizer": cfg.optimizer, "lr_schedule": cfg.lr_schedule,
           "obs_norm": cfg.obs_norm, "fc_init_gain": cfg.fc_init_gain, "seed": cfg.seed, "cap_seconds": cap,
           "train_episodes": len(train_eps), "held_out_frames": sum(len(e) - 1 for e in held_out),
           "curve": [{"step": 0, "frames": 0, "seconds": 0.0, **first}]}
    reached: dict[float, dict] = {}
    seconds, step, compile_seconds, next_eval = 0.0, 0, None, eval_every
    while seconds < cap and len(reached) < len(TARGETS):
        chunk = stream.next_chunk()
        t0 = time.perf_counter()
        loss = trainer.step(chunk)
        dt = time.perf_counter() - t0
        if compile_seconds is None:
            compile_seconds = dt
        seconds += dt
        step += 1
        if not np.isfinite(loss):
            row["diverged_at"] = step
            break
        if step >= next_eval or seconds >= cap:
            next_eval = step + max(eval_every, round(0.05 * step))  # 5 % of the steps once past 20 evaluations
            point = {"step": step, "frames": step * frames_per_step, "seconds": seconds, "loss": loss, **ratio_now()}
            row["curve"].append(point)
            print(f"{name}: step {step} ({seconds:.0f} s) excess ratio {point['ratio']:.3f}", file=sys.stderr, flush=True)
            for target in TARGETS:
                if target not in reached and point["ratio"] < target:
                    reached[target] = {"seconds": seconds, "frames": point["frames"], "step": step}
    last = row["curve"][-1]
    full = evaluate(variant, trainer.params(), held_out, cfg.unroll)
    row.update(copy_bce=full["copy_bce"], floor=full["target_entropy"], steps=step, train_seconds=seconds,
               compile_seconds=compile_seconds, frames_per_second=step * frames_per_step / max(seconds, 1e-9),
               ratio_at_end=last["ratio"], bce_at_end=last["bce"])
    for target in TARGETS:
        hit = reached.get(target)
        key = f"to_{target:g}"
        row[key] = hit if hit is not None else {"reached": False, "ratio_at_cap": last["ratio"], "seconds": seconds}
    return row


def main(argv=None) -> int:
    args = _parse(argv)
    caps = {name: args.cap for name in args.rows}
    for item in args.caps:
        name, _, value = item.partition("=")
        if name not in ROWS:
            raise SystemExit(f"--caps: unknown row {name!r}; rows are {list(ROWS)}")
        caps[name] = float(value)
    if "small-fast-onednn" in args.rows and "small-fast-torch" in args.rows[args.rows.index("small-fast-onednn"):]:
        raise SystemExit("--rows: run small-fast-torch before small-fast-onednn (oneDNN's OpenMP teams slow PyTorch's "
                         "for the rest of the process)")
    if args.quick:
        caps = {name: 5.0 for name in args.rows}
        args.episodes, args.episode_steps, args.eval_every = 8, 40, 2
    if args.compile_cache:
        compile_cache.use(args.compile_cache)
    if args.prime:
        for name in args.rows:
            prime_row(name, args)
        return 0
    if any(ROWS[r]["framework"] == "torch" for r in args.rows):
        import torch

        torch.set_num_threads(args.torch_threads or os.cpu_count())
    result = {"benchmark": "time_to_quality", "variant": "main", "data": "built-in game, behaviour switching",
              "episodes": args.episodes, "episode_steps": args.episode_steps, "level": args.level,
              "cpu_count": os.cpu_count(), "python": platform.python_version(), "jax_version": jax.__version__,
              "load_avg_start": os.getloadavg()[0], "quick": args.quick, "rows": []}
    for name in args.rows:
        result["rows"].append(run_row(name, args, caps[name]))
    result["load_avg_end"] = os.getloadavg()[0]
    warn_if_busy(result, result["load_avg_start"], result["load_avg_end"])
    rows = {r["row"]: r for r in result["rows"]}
    for mine, key in (("small-fast", "cdrl_over_torch_seconds_to_1"),
                      ("small-fast-warm", "cdrl_warm_over_torch_seconds_to_1"),
                      ("small-fast-onednn", "cdrl_onednn_over_torch_seconds_to_1")):
        if mine in rows and "small-fast-torch" in rows:
            a, b = rows[mine].get("to_1"), rows["small-fast-torch"].get("to_1")
            if a.get("reached", True) and b.get("reached", True):
                result[key] = a["seconds"] / b["seconds"]
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
