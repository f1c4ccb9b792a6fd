"""The `cdrl` command line: collect, train, sweep, lr-search, eval, plot, variants, learners.

Every `train` option is a field of `cdrl.runs.config.RunConfig`; its help text and default come
from there, so the CLI and the Python API cannot drift apart.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from cdrl.cli_report import USER_ERRORS, cmd_eval, cmd_plot
from cdrl.data.gymrec import OBS_MODES
from cdrl.evaluation.play import TEST_SEED
from cdrl.options import SECTIONS, section_of
from cdrl.runs import compile_cache
from cdrl.runs.config import RECIPES, RunConfig
from cdrl.runs.sweep import GRID_FIELDS

# Option -> its old spellings, still accepted for one release.
OLD_OPTION_NAMES = {"learner": ("--controller",)}
LR_CANDIDATES = (3.0, 1.0, 0.5, 0.2, 0.1, 0.05, 0.02, 0.01)
LR_THRESHOLD = 1.0
_TYPES = {"int": int, "float": float, "str": str}  # RunConfig's field annotations (bool: --x/--no-x)
SECTION_OF = section_of()
ALLOW_DATA_CHANGE_HELP = ("with --resume: go on although the data set changed since the run began (the run's "
                          "data.json records the change and the step); without it such a resume is refused, "
                          "naming what changed")
DISTRIBUTED_HELP = ("join the processes of a multi-process run with jax.distributed (every process runs this same "
                    "command): from JAX_COORDINATOR_ADDRESS (host:port of process 0), JAX_NUM_PROCESSES and "
                    "JAX_PROCESS_ID, or a cluster JAX detects (SLURM's srun); the {what} spread over every device "
                    "of every process (--devices 0) unless --devices says otherwise; process 0 prints")


def _add_config_options(parser: argparse.ArgumentParser, several: tuple[str, ...] = (), skip: tuple[str, ...] = ()) -> None:
    """One option per `RunConfig` field. Options not given stay absent from the namespace, so
    a resumed run changes only what the command line names. Fields in `several` take one or
    more values (a sweep's grid)."""
    groups = {name: parser.add_argument_group(f"{name} options", cls.__doc__.splitlines()[0])
              for name, cls in SECTIONS.items()}
    for f in dataclasses.fields(RunConfig):
        if f.name in skip:
            continue
        group = groups[SECTION_OF[f.name]]
        grid = f.name in several
        if f.metadata.get("recipe"):
            default = "from --recipe: " + ", ".join(f"{name} {table[f.name]}" for name, table in RECIPES.items())
        else:
            default = f.default
        if f.type == "bool":
            group.add_argument("--" + f.name.replace("_", "-"), action=argparse.BooleanOptionalAction,
                                default=argparse.SUPPRESS, help=f"{f.metadata['help']} (default: {default})")
            continue
        group.add_argument(
            "--" + f.name.replace("_", "-"), *OLD_OPTION_NAMES.get(f.name, ()),
            type=_TYPES[f.type],
            nargs="+" if grid else None,
            default=argparse.SUPPRESS,
            help=f"{f.metadata['help']}{'; several values sweep them' if grid else ''} (default: {default})",
        )


def _options(args, skip: tuple[str, ...] = ()) -> dict:
    return {f.name: getattr(args, f.name) for f in dataclasses.fields(RunConfig)
            if hasattr(args, f.name) and f.name not in skip}


def _distributed(args, options: dict) -> bool:
    """`--distributed`: join the run's processes (`cdrl.runs.distributed.initialize`, before JAX
    starts its backends); the run then spreads over every device of every process unless
    `--devices` says otherwise. Returns whether this process writes what the run prints."""
    if not args.distributed:
        return True
    from cdrl.runs.distributed import initialize

    joined = initialize()
    options.setdefault("devices", 0)
    return joined["process"] == 0


def _check_allow_data_change(args) -> None:
    if args.allow_data_change and not args.resume:
        raise ValueError("--allow-data-change is for --resume: a new run records the data it starts with")


def _cmd_train(args) -> int:
    from cdrl.runs.train import train_run

    options = _options(args)
    try:
        _check_allow_data_change(args)
        prints = _distributed(args, options)
        if args.resume:
            summary = train_run(None, args.resume, resume=True, overrides=options,
                                allow_data_change=args.allow_data_change)
        else:
            summary = train_run(RunConfig(**options), args.run_dir)
    except USER_ERRORS as exc:
        print(f"cdrl train: {exc}", file=sys.stderr)
        return 2
    if prints:
        print(json.dumps(summary))
    return 0


def _cmd_sweep(args) -> int:
    from cdrl.analysis.plots import plot_sweep
    from cdrl.runs.sweep import Grid, format_results, resume_sweep, sweep_run

    grid = {name: tuple(getattr(args, name)) for name in GRID_FIELDS if hasattr(args, name)}
    run_dir = args.resume or args.run_dir
    options = _options(args) if args.resume else _options(args, skip=GRID_FIELDS)
    try:
        _check_allow_data_change(args)
        prints = _distributed(args, options)
        if args.resume:
            rows = resume_sweep(args.resume, overrides=options, allow_data_change=args.allow_data_change)
        else:
            rows = sweep_run(RunConfig(**options), Grid(**grid), args.run_dir)
    except USER_ERRORS as exc:
        print(f"cdrl sweep: {exc}", file=sys.stderr)
        return 2
    if not prints:
        return 0
    plot_sweep(run_dir)
    print(format_results(rows))
    print(json.dumps(json.loads((Path(run_dir) / "results.json").read_text())))
    return 0


def _cmd_lr_search(args) -> int:
    from cdrl.runs.sweep import lr_search

    try:
        result = lr_search(RunConfig(**_options(args, skip=("lr", "steps", "diverge_threshold", "seed"))),
                           args.candidates, args.probe_steps, args.threshold, seeds=getattr(args, "seed", ()))
    except USER_ERRORS as exc:
        print(f"cdrl lr-search: {exc}", file=sys.stderr)
        return 2
    for c in result["candidates"]:
        why = c["rejected"]
        verdict = "ok" if why is None else (
            f"rejected at step {why['step']}{'' if len(result['seeds']) == 1 else ' of seed ' + str(why['seed'])}: "
            f"{why['group']} ratio {why['ratio']:.3g}" + ("" if why["finite"] else " (non-finite)"))
        print(f"lr {c['lr']:<8g} largest kernel ratio {c['max_ratio']:<10.3g} {verdict}")
    chosen = result["chosen"]
    print(f"chosen learning rate: {chosen:g}" if chosen is not None else
          "no candidate stayed under the threshold: try lower rates")
    print(json.dumps(result))
    return 0 if chosen is not None else 1


def _use_cpu_devices(count: int) -> None:
    """Ask for ``count`` devices of JAX's CPU backend in this process, where it has fewer and
    has not started yet (a GPU or TPU backend is left as it is)."""
    import jax

    if count > 1 and jax.config.jax_num_cpu_devices < count:
        try:
            jax.config.update("jax_num_cpu_devices", count)
        except RuntimeError:  # JAX already started: games_sharding names the devices there are
            pass


def _cmd_collect(args) -> int:
    from cdrl.data import gymrec
    from cdrl.data.collect import collect

    try:
        if args.env:
            for name in ("batch_size", "devices", "max_filter"):
                if getattr(args, name) is not None:
                    raise ValueError(f"--{name.replace('_', '-')} is for the built-in game (no --env)")
            gymrec.record_env(args.env, Path(args.out), args.episodes, size=args.obs_size, crop=args.crop,
                              obs=args.obs or "image", policy=args.policy or "uniform", seed=args.seed,
                              max_steps=args.episode_steps, env_kwargs=gymrec.parse_env_kwargs(args.env_kwargs))
        else:
            for name in ("obs", "crop", "env_kwargs"):
                if getattr(args, name):
                    raise ValueError(f"--{name.replace('_', '-')} is for a gymnasium game (--env ID)")
            devices = 1 if args.devices is None else args.devices
            _use_cpu_devices(devices)
            collect(Path(args.out), args.episodes, policy=args.policy or "behaviour", seed=args.seed,
                    max_steps=args.episode_steps, obs_size=args.obs_size,
                    max_filter=1 if args.max_filter is None else args.max_filter,
                    batch_size=16 if args.batch_size is None else args.batch_size, devices=devices)
    except USER_ERRORS as exc:
        print(f"cdrl collect: {exc}", file=sys.stderr)
        return 2
    print(args.out)
    return 0


def _cmd_variants(args) -> int:
    from cdrl.models import VARIANTS

    for name, cls in sorted(VARIANTS.items()):
        print(f"{name:20s} {(cls.__doc__ or '').strip().splitlines()[0] if cls.__doc__ else ''}")
    return 0


def _cmd_learners(args) -> int:
    from cdrl import learners

    old = {}
    for alias, name in learners.ALIASES.items():
        old.setdefault(name, []).append(alias)
    print(f"{learners.OFFLINE:20s} the world model alone, offline on recorded episodes (old name: none)")
    for name, cls in learners.LEARNERS.items():
        doc = " ".join((sys.modules[cls.__module__].__doc__ or "").split("\n\n")[0].split())
        aliases = f" (old name: {', '.join(old[name])})" if name in old else ""
        print(f"{name:20s} {doc.split(': ', 1)[-1]}{aliases}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="cdrl", description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--compile-cache", metavar="DIR", type=Path, default=compile_cache.cache_dir(),
                        help="keep compiled programs in DIR, so that a second run of the same configuration "
                             "compiles nothing (default: $CDRL_COMPILE_CACHE, else $JAX_COMPILATION_CACHE_DIR, "
                             "else ~/.cache/cdrl/xla; now %(default)s)")
    common.add_argument("--no-compile-cache", action="store_true",
                        help="compile every program afresh and keep nothing on disk")
    sub = parser.add_subparsers(dest="command", required=True)

    def command(name: str, **kwargs) -> argparse.ArgumentParser:  # every command takes the common options
        return sub.add_parser(name, parents=[common], **kwargs)

    train = command("train", help="train a model variant (the main job)")
    train.add_argument("--run-dir", default="runs/run", help="directory of the run's outputs (default: runs/run)")
    train.add_argument("--resume", metavar="RUN_DIR", default=None,
                       help="continue the run in RUN_DIR from its last good checkpoint (default: none)")
    train.add_argument("--distributed", action="store_true", help=DISTRIBUTED_HELP.format(what="B streams"))
    train.add_argument("--allow-data-change", action="store_true", help=ALLOW_DATA_CHANGE_HELP)
    _add_config_options(train)
    train.set_defaults(func=_cmd_train)

    sw = command("sweep", help="train a grid of configurations (any of --lr --momentum --b2 --weight-decay --grad-clip --lr-warmup --seed --diverge-threshold with several values) as one vmapped program")
    sw.add_argument("--run-dir", default="runs/sweep", help="directory of the sweep's runs and table (default: runs/sweep)")
    sw.add_argument("--resume", metavar="SWEEP_DIR", default=None,
                    help="continue the sweep in SWEEP_DIR from its last complete checkpoint; only --steps, "
                         "--checkpoint-every, --keep-checkpoints, --eval-every, --eval-episodes, --devices, "
                         "--tensorboard may change (default: none)")
    sw.add_argument("--distributed", action="store_true", help=DISTRIBUTED_HELP.format(what="configurations"))
    sw.add_argument("--allow-data-change", action="store_true", help=ALLOW_DATA_CHANGE_HELP)
    _add_config_options(sw, several=GRID_FIELDS)
    sw.set_defaults(func=_cmd_sweep)

    ls = command("lr-search", help="the thesis's learning-rate search: the highest rate whose norm ratios "
                                          "stay under a threshold over a probe budget (candidates run in parallel)")
    ls.add_argument("--candidates", type=float, nargs="+", default=list(LR_CANDIDATES),
                    help=f"learning rates to probe (default: {' '.join(map(str, LR_CANDIDATES))})")
    ls.add_argument("--probe-steps", type=int, default=50, help="training steps of the probe (default: 50)")
    ls.add_argument("--threshold", type=float, default=LR_THRESHOLD,
                    help=f"largest allowed kernel norm ratio ||grad||/||param|| (default: {LR_THRESHOLD})")
    _add_config_options(ls, several=("seed",), skip=("lr", "steps", "diverge_threshold"))
    ls.set_defaults(func=_cmd_lr_search)

    ev = command("eval", help="evaluate trained runs on their held-out episodes and print a table")
    ev.add_argument("run_dirs", nargs="*", metavar="RUN_DIR")
    ev.add_argument("--episodes", type=int, default=None,
                    help="held-out episodes (with --policy: games per policy) (default: the run's eval_episodes)")
    ev.add_argument("--horizon", metavar="K", type=int, default=None,
                    help="also score predictions K steps ahead: after --context real frames the model is fed its "
                         "own predictions, the excess ratio at every step 1 .. K against copying the last real "
                         "frame for as long (default: none)")
    ev.add_argument("--context", metavar="C", type=int, default=8,
                    help="with --horizon: real frames the model sees before it runs open loop")
    ev.add_argument("--policy", metavar="RUN_DIR", default=None,
                    help="play the controller of RUN_DIR against the random and behaviour-switching policies "
                         "on the same seeds: mean return with a 95%% CI, episode length (default: none)")
    ev.add_argument("--video", action="store_true",
                    help="with --policy: also write RUN_DIR/policy.gif, a test game of the policy: the screen, its "
                         "view, its buttons and a planner's plans")
    ev.add_argument("--video-seed", type=int, default=TEST_SEED,
                    help=f"with --video: the game's seed (default: {TEST_SEED}, the first test game)")
    ev.add_argument("--imagination", metavar="RUN_DIR", default=None,
                    help="whether the world model of RUN_DIR (a controller variant on the built-in game) imagines "
                         "which way to steer: imagined against real returns of four button sequences from the "
                         "states of privileged play; writes RUN_DIR/imagination.json and imagination.gif "
                         "(docs/evaluation.md) (default: none)")
    ev.add_argument("--games", type=int, default=32,
                    help="with --imagination: games the privileged policy plays (default: 32)")
    ev.add_argument("--every", type=int, default=10, help="with --imagination: steps between the starts (default: 10)")
    ev.add_argument("--out", metavar="FILE", default=None,
                    help="with --imagination: the JSON file (default: RUN_DIR/imagination.json)")
    ev.add_argument("--reward-from", choices=("lookahead", "variant"), default=None,
                    help="with --imagination: the reward head that scores imagined steps (default: the look-ahead's "
                         "where the run trains one, else the variant's)")
    ev.add_argument("--no-video", action="store_true",
                    help="with --imagination: write no RUN_DIR/imagination.gif of real and imagined frames")
    ev.set_defaults(func=cmd_eval)

    plot = command("plot", help="write the thesis's figures of one or more runs as PNG files")
    plot.add_argument("run_dirs", nargs="+", metavar="RUN_DIR")
    plot.add_argument("--out", default=None, help="output directory (default: RUN_DIR/plots of the first run)")
    plot.add_argument("--groups", nargs="+", default=None, metavar="GROUP",
                      help="parameter groups of the norm-ratio figure, e.g. obs_enc/conv3/kernel "
                           "(default: the thesis's encoder layer 4 and decoder layer 3 kernels)")
    plot.set_defaults(func=cmd_plot)

    col = command("collect", help="record episodes of the built-in game, or of any gymnasium game (--env), "
                                          "to a data set directory")
    col.add_argument("out", metavar="OUT_DIR")
    col.add_argument("--episodes", type=int, default=100, help="number of episodes (default: 100)")
    col.add_argument("--policy", choices=["behaviour", "uniform"], default=None,
                     help="behaviour switching (observation data, built-in game only) or uniform random over the "
                          "action space (action data) (default: behaviour; uniform with --env)")
    col.add_argument("--seed", type=int, default=0, help="seed of the games and the policy (default: 0)")
    col.add_argument("--episode-steps", type=int, default=500, help="step limit of an episode (default: 500)")
    col.add_argument("--obs-size", type=int, default=150,
                     help="side of the square observation: 64 for the small preset, 16 for tiny (default: 150)")
    col.add_argument("--max-filter", type=int, default=None,
                     help="built-in game: side of the max filter applied before shrinking to --obs-size, 5 for "
                          "preset small-max (default: 1, none)")
    col.add_argument("--batch-size", type=int, default=None,
                     help="built-in game: episodes simulated together as one vmapped program (default: 16)")
    col.add_argument("--devices", type=int, default=None,
                     help="built-in game: spread each batch of episodes over this many devices of this process (0: "
                          "all; on the CPU: host devices, made as many as asked, one per core is best; the batch "
                          "size a multiple of it); the episodes are the same for any count (default: 1)")
    col.add_argument("--env", metavar="ID", default=None,
                     help="record this registered gymnasium game instead of the built-in one, e.g. CartPole-v1, or "
                          "ALE/Pong-v5 with ale-py installed; MODULE:ID imports MODULE first, for a game that a "
                          "package registers when imported (gymnasium's module:ID form, e.g. ale_py:ALE/Pong-v5) "
                          "(Discrete actions are recorded one-hot, Box actions rescaled to [0, 1]) (default: none)")
    col.add_argument("--obs", choices=OBS_MODES, default=None,
                     help="with --env: record the observations (image) or env.render() frames of "
                          "render_mode='rgb_array' (render: for games whose observations are not images) "
                          "(default: image)")
    col.add_argument("--crop", type=int, nargs=4, metavar=("TOP", "LEFT", "HEIGHT", "WIDTH"), default=None,
                     help="with --env: the part of each frame to keep, its sides multiples of --obs-size "
                          "(default: the largest such central square)")
    col.add_argument("--env-kwargs", nargs="+", metavar="KEY=VALUE", default=None,
                     help="with --env: options of gymnasium.make, as key=value items or one JSON object, "
                          "e.g. is_slippery=false (default: none)")
    col.set_defaults(func=_cmd_collect)

    var = command("variants", help="list the model variants")
    var.set_defaults(func=_cmd_variants)
    lrn = command("learners", help="list the learners a run can name with --learner")
    lrn.set_defaults(func=_cmd_learners)
    return parser


def main(argv: list[str] | None = None) -> int:
    if argv is None:  # the `cdrl` command itself, not a call from Python: run it under tcmalloc
        from cdrl.runs.allocator import reexec_with_allocator

        try:
            reexec_with_allocator()
        except ValueError as exc:
            print(f"cdrl: {exc}", file=sys.stderr)
            return 2
    args = build_parser().parse_args(argv)
    if not args.no_compile_cache:
        compile_cache.use(args.compile_cache)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
