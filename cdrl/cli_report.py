"""The `cdrl eval` and `cdrl plot` commands: reports on finished runs (`cdrl.cli` parses their options)."""
from __future__ import annotations

import json
import sys
from pathlib import Path

# What a command reports as its error (a message, exit 2) rather than a traceback: bad input
# (ValueError, its DatasetError and DataChangedError), files (OSError), and runs and
# checkpoints that cannot go on (RuntimeError: CheckpointError, DivergenceError, LockedError).
USER_ERRORS = (ValueError, OSError, RuntimeError)


def cmd_eval(args) -> int:
    for name, least in (("games", 1), ("every", 1), ("video_seed", 0)):
        if getattr(args, name) < least:
            print(f"cdrl eval: --{name.replace('_', '-')} must be at least {least}, got {getattr(args, name)}",
                  file=sys.stderr)
            return 2
    if args.video and not args.policy:
        print("cdrl eval: --video records a game of a learned policy; give --policy RUN_DIR", file=sys.stderr)
        return 2
    if args.policy:
        return _eval_policy(args)
    if args.imagination:
        return _eval_imagination(args)
    if not args.run_dirs:
        print("cdrl eval: give RUN_DIR(s), --policy RUN_DIR or --imagination RUN_DIR", file=sys.stderr)
        return 2
    from cdrl.analysis.report import eval_runs

    try:
        rows = eval_runs([Path(p) for p in args.run_dirs], episodes=args.episodes, horizon=args.horizon,
                         context=args.context)
    except USER_ERRORS as exc:
        print(f"cdrl eval: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(rows))
    return 0


def _eval_policy(args) -> int:
    from cdrl.evaluation.play import format_table
    from cdrl.analysis.policy_video import policy_run_video
    from cdrl.runs.online import eval_policy_run

    try:
        rows = eval_policy_run(Path(args.policy), episodes=args.episodes)
        video = policy_run_video(Path(args.policy), args.video_seed) if args.video else None
    except USER_ERRORS as exc:
        print(f"cdrl eval: {exc}", file=sys.stderr)
        return 2
    print(format_table(rows))
    print(json.dumps(rows))
    if video:
        print(f"wrote {video}")
    return 0


def _eval_imagination(args) -> int:
    from cdrl.analysis.imagination_video import imagination_report, summary

    try:
        result, written = imagination_report(Path(args.imagination), games=args.games, every=args.every,
                                             out=args.out, video=not args.no_video, reward_from=args.reward_from)
    except USER_ERRORS as exc:
        print(f"cdrl eval: {exc}", file=sys.stderr)
        return 2
    print(summary(result))
    for path in written:
        print(f"wrote {path}")
    return 0


def cmd_plot(args) -> int:
    from cdrl.analysis.plots import plot_runs

    try:
        written = plot_runs([Path(p) for p in args.run_dirs], out_dir=Path(args.out) if args.out else None,
                            groups=args.groups)
    except USER_ERRORS as exc:
        print(f"cdrl plot: {exc}", file=sys.stderr)
        return 2
    for path in written:
        print(path)
    return 0
