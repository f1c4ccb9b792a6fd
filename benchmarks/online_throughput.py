"""Throughput of the online programs: game frames per second of a run that plays as it learns.

Each learner is the program `cdrl train` builds for it (`cdrl.runs.online.learner`): B games
(`--games`, default 8) simulated and drawn at 150 x 150, resized to the preset's frames, the
model acting in them for T steps and learning from them, all in one jitted step. Frames per
step are B x T (the games' steps). Learners (`--learners`, any subset):

  rollout   final_proposal, the thesis's online learner (reward ascent through the chunk), the
            ascent on from the first update (`--warmup-steps 0`: before it is on, a step takes
            one backward pass less, as with `--scope all`)
  rollout-all  the same with `--scope all`
  real      final_proposal with the replay buffer, 4 model updates a chunk and the actor-critic
            on the chunk just played (`--controller real --scope all`)
  ppo       PPO's program at its own 16 games x 32 steps
  critic-look  the actor-critic in imagination, 5 imagined steps, its model trained with the
            look-ahead (`--lookahead-steps 3`)
  planner   `mpc_planner` on the same model: 8 plans of 5 imagined steps at every game step

at the presets of `--presets` (small, thesis). The first step's seconds are reported as its
compile time (JAX's persistent cache off: a real compile).

With `--baseline DIR` (a checkout of another commit, e.g. `git worktree add /tmp/base HEAD~1`)
each configuration also runs from DIR's code, in a second process, the two timed in
alternating windows (which goes first alternates too): `speedup` is the median [min, max] of
the per-repeat ratios (this tree / DIR), both commits measured in one run under the same load.
A checkout from before `cdrl.runs.online.learner` (such as 8b48636, the reference of the speed
targets) can be the baseline of `rollout` and `rollout-all`: its program is built as that
checkout built it.

    .venv/bin/python benchmarks/online_throughput.py --baseline /tmp/base --out FILE
    .venv/bin/python benchmarks/online_throughput.py --quick       # seconds: does it run?

One JSON line at the end (`--out FILE` also writes it there).
"""
from __future__ import annotations

import argparse
import contextlib
import multiprocessing as mp
import os
import statistics
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LEARNERS = {
    "rollout": dict(variant="final_proposal", controller="rollout", warmup_steps=0),
    "rollout-all": dict(variant="final_proposal", controller="rollout", scope="all", warmup_steps=0),
    "real": dict(variant="final_proposal", controller="real", scope="all"),
    "ppo": dict(variant="ppo"),
    "critic-look": dict(variant="final_proposal", learner="imagination_ac", horizon=5, lookahead_steps=3),
    "planner": dict(variant="final_proposal", learner="mpc_planner", horizon=5, lookahead_steps=3),
}


def _parse(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--learners", nargs="+", default=["rollout", "real", "ppo"], choices=list(LEARNERS))
    ap.add_argument("--presets", nargs="+", default=["small", "thesis"], choices=["tiny", "small", "thesis"])
    ap.add_argument("--games", type=int, default=8, help="games B of rollout and real (default: 8; ppo: 16)")
    ap.add_argument("--seconds", type=float, default=None, help="timing window (default 3; --quick: 0.5)")
    ap.add_argument("--repeats", type=int, default=None, help="windows per configuration (default 5; --quick: 2)")
    ap.add_argument("--baseline", default=None, metavar="DIR",
                    help="also run each configuration from another checkout, alternating windows with this tree's")
    ap.add_argument("--this-malloc", choices=["system", "command"], default="system",
                    help="this tree's programs on glibc's malloc (default) or on the one the `cdrl` command picks "
                         "(tcmalloc where installed); the baseline's always on glibc's, as the command ran "
                         "before it picked one (a056e15)")
    ap.add_argument("--quick", action="store_true", help="tiny preset, short windows: a smoke run")
    ap.add_argument("--out", default=None, help="also write the JSON line to this file")
    return ap.parse_args(argv)


class _Program:
    """One learner's program at one preset, compiled and run once, its state carried on."""

    def __init__(self, learner: str, preset: str, games: int):
        import jax

        jax.config.update("jax_enable_compilation_cache", False)  # compile times are real compiles
        from cdrl.runs.config import RunConfig
        try:
            from cdrl.runs.online import build_learner
        except ImportError:  # a checkout from before the learner interface
            build_learner = None
        try:
            from cdrl.runs.online import learner as build
        except ImportError:  # a checkout from before the learners' builder
            build = None

        options = dict(LEARNERS[learner], preset=preset, seed=0)
        if learner != "ppo":
            options["batch"] = games
        if build_learner is not None:
            cfg = RunConfig(**options)
            self.program = _interface_program(build_learner(cfg))
        elif build is not None:
            cfg = RunConfig(**options)
            self.program = build(cfg)
        elif options.pop("controller", None) == "rollout":
            cfg, self.program = _rollout_before_builder(options)
        else:
            raise ValueError(f"learner {learner!r}: this checkout has no cdrl.runs.online.learner to build it")
        self.state = self.program.fresh(0)
        jax.block_until_ready(self.state)
        self.frames_per_step = cfg.batch * cfg.unroll
        t0 = time.perf_counter()
        self._step()
        self.compile_s = time.perf_counter() - t0
        self.describe = {"learner": learner, "preset": preset, "games": cfg.batch, "unroll": cfg.unroll,
                         "frames_per_step": self.frames_per_step}

    def _step(self):
        import jax

        self.state, metrics = self.program.program(self.state)
        jax.block_until_ready(metrics)

    def window(self, seconds: float) -> float:
        """Game frames per second over one window of whole steps."""
        n, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            self._step()
            n += 1
        return n * self.frames_per_step / (time.perf_counter() - t0)


def _interface_program(learner):
    """(fresh, program) of a learner behind `cdrl.learners.api.Learner`."""
    import types

    import jax

    from cdrl.learners.api import train_program

    return types.SimpleNamespace(fresh=lambda seed: learner.init(jax.random.PRNGKey(seed)),
                                 program=lambda state: train_program(learner, state))


def _rollout_before_builder(options: dict):
    """(config, program) of the thesis's online learner as checkouts from before
    `cdrl.runs.online.learner` build it (such as 8b48636, the reference of the speed targets):
    the same program, `final_proposal` with the reward ascent through the chunk, from the
    `RunConfig` options of `options` (their only learner then)."""
    import types

    import jax

    from cdrl.models import make_variant
    from cdrl.runs.config import RunConfig
    from cdrl.runs.online import hparams
    from cdrl.runs.sources import run_game
    from cdrl.training.online import OnlineConfig, init_online, online_step

    cfg = RunConfig(**options)
    variant = make_variant(cfg.variant, cfg.arch)
    game, env_params = run_game(cfg)
    ocfg, hp = OnlineConfig(num_envs=cfg.batch, unroll=cfg.unroll), hparams(cfg)
    init = jax.jit(init_online, static_argnums=(0, 1, 3))
    return cfg, types.SimpleNamespace(
        fresh=lambda seed: init(variant, game, env_params, ocfg, jax.random.PRNGKey(seed), hp),
        program=lambda state: online_step(variant, game, ocfg, state, hp, env_params))


def _worker(root: str, learner: str, preset: str, games: int, conn) -> None:
    """Serves timing windows of one checkout's program: answers each `seconds` received on `conn`
    with the window's frames/s, until it receives None."""
    sys.path.insert(0, root)
    import cdrl

    if not os.path.abspath(cdrl.__file__).startswith(os.path.abspath(root) + os.sep):
        raise RuntimeError(f"cdrl imported from {cdrl.__file__}, not from {root}")
    p = _Program(learner, preset, games)
    conn.send({**p.describe, "compile_s": p.compile_s, "malloc": os.environ.get("CDRL_MALLOC_PRELOADED", "system")})
    while (seconds := conn.recv()) is not None:
        conn.send(p.window(seconds))


def _spread(values) -> dict:
    return {"repeats": [round(v, 3) for v in values], "min": min(values), "median": statistics.median(values),
            "max": max(values)}


@contextlib.contextmanager
def _malloc(choice: str):
    """This process's environment, for the while, preloading the malloc `choice` picks
    (`cdrl.runs.allocator`: "command" as the `cdrl` command picks it, "system" glibc's)."""
    from cdrl.runs.allocator import allocator_library, preload_environment

    env = preload_environment(dict(os.environ), allocator_library("auto" if choice == "command" else "system"))
    saved = dict(os.environ)
    os.environ.update(env or {})
    try:
        yield
    finally:
        os.environ.clear()
        os.environ.update(saved)


def measure(learner: str, preset: str, args, seconds: float, repeats: int) -> dict:
    """One configuration: this tree's program (and the baseline's, alternating windows)."""
    from common import alternate_windows, recv_or_fail

    ctx = mp.get_context("spawn")
    roots = [ROOT] + ([os.path.abspath(args.baseline)] if args.baseline else [])
    pipes, workers, described = [], [], []
    for root in roots:  # one after the other: each compiles on an otherwise idle machine
        mine, theirs = ctx.Pipe()
        w = ctx.Process(target=_worker, args=(root, learner, preset, args.games, theirs))
        with _malloc(args.this_malloc if root == ROOT else "system"):
            w.start()  # a spawned process starts with the environment of this moment
        pipes.append(mine)
        workers.append(w)
        described.append(recv_or_fail(mine, w))
    rates = alternate_windows(pipes, workers, seconds, repeats)
    row = {**described[0], "frames_per_s": _spread(rates[0])}
    if args.baseline:
        row["baseline_compile_s"] = described[1]["compile_s"]
        row["baseline_malloc"] = described[1]["malloc"]
        row["baseline_frames_per_s"] = _spread(rates[1])
        row["speedup"] = _spread([a / b for a, b in zip(rates[0], rates[1])])
    return row


def main(argv=None) -> int:
    from common import checkout_commit, finish  # here: a worker process must not import cdrl before its checkout's

    args = _parse(argv)
    seconds = args.seconds or (0.5 if args.quick else 3.0)
    repeats = args.repeats or (2 if args.quick else 5)
    presets = ["tiny"] if args.quick else args.presets
    result = {"benchmark": "online_throughput", "cpu_count": os.cpu_count(), "commit": checkout_commit(ROOT),
              "baseline": args.baseline, "baseline_commit": args.baseline and checkout_commit(args.baseline),
              "seconds_per_repeat": seconds, "repeats": repeats, "load_avg_start": round(os.getloadavg()[0], 2),
              "rows": []}
    for preset in presets:
        for learner in args.learners:
            row = measure(learner, preset, args, seconds, repeats)
            result["rows"].append(row)
            fps = row["frames_per_s"]
            line = (f"{learner:8s} {preset:6s} B {row['games']:2d} T {row['unroll']:2d}: {fps['median']:8.1f} frames/s "
                    f"[{fps['min']:.1f}, {fps['max']:.1f}], compile {row['compile_s']:.1f} s")
            if args.baseline:
                sp, base = row["speedup"], row["baseline_frames_per_s"]
                line += (f"; baseline {base['median']:.1f} frames/s, compile {row['baseline_compile_s']:.1f} s; "
                         f"this tree / baseline {sp['median']:.2f}x [{sp['min']:.2f}, {sp['max']:.2f}]")
            print(line, flush=True)
    return finish(result, args.out)


if __name__ == "__main__":
    sys.exit(main())
