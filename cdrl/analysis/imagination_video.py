"""`cdrl eval --imagination RUN_DIR`: the imagination probe of a run, and imagination you can watch.

`imagination_report` runs `cdrl.evaluation.imagination_probe.probe` on a run's newest checkpoint
and writes its figures as JSON. Beside them, an animated GIF shows imagination at work: from a
few real states of the first followed game, each of the four button sequences plays `steps`
open-loop steps in the game (left) and in the model's imagination (right). Under each pair are
the step's real reward, the imagined one, and the value head's value of the imagined state.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from cdrl.analysis.animation import write_gif
from cdrl.evaluation import imagination_probe as ip

CELL = 96  # the least side of a frame in the video; frames are scaled up by a whole factor
PAD = 4
HEADER = 14  # one line of text above the frames
TEXT = 24  # two lines of text under each pair of frames
WATCH_STARTS = 4
FRAME_MS = 250


def watch(variant, params, game, env_params, hp, *, starts: int = WATCH_STARTS, every: int = 10,
          steps: int = ip.HORIZON, source: str | None = None) -> dict:
    """The first followed game's branches at `starts` starts, `every` steps apart, with their
    frames (`imagination_probe.followed_branches`, game 0): `[starts, sequences, steps, ...]`."""
    b = ip.followed_branches(variant, params, game, env_params, hp, games=1, points=starts, every=every,
                             horizon=steps, frames=True, source=source)
    return {name: b[name][0] for name in ("real", "imagined", "value", "on", "real_frames", "imagined_frames")}


def frame_images(watched: dict, with_value: bool) -> list:
    """One grey-scale PIL image per start and step: per sequence, the real frame beside the
    imagined one, the rewards (and the value, `with_value`) written under them."""
    from PIL import Image, ImageDraw

    starts, sequences, steps, size, _ = watched["real_frames"].shape
    scale = max(1, -(-CELL // size))
    cell = size * scale
    width, row = 2 * cell + 3 * PAD, cell + TEXT + PAD
    names = list(ip.SEQUENCES)

    def pixels(frame):
        return np.kron(np.clip(frame, 0.0, 1.0) * 255.0, np.ones((scale, scale))).astype(np.uint8)

    images = []
    for s in range(starts):
        for k in range(steps):
            image = Image.new("L", (width, HEADER + sequences * row), 0)
            draw = ImageDraw.Draw(image)
            draw.text((PAD, 1), f"start {s + 1}/{starts} step {k + 1}/{steps}: real | imagined", fill=255)
            for j in range(sequences):
                top = HEADER + j * row
                image.paste(Image.fromarray(pixels(watched["real_frames"][s, j, k])), (PAD, top))
                image.paste(Image.fromarray(pixels(watched["imagined_frames"][s, j, k])), (2 * PAD + cell, top))
                value = f" V {watched['value'][s, j, k]:+.2f}" if with_value else ""
                draw.text((PAD, top + cell + 1), f"{names[j]}: real r {watched['real'][s, j, k]:+.2f}", fill=255)
                draw.text((PAD, top + cell + 12), f"imagined r {watched['imagined'][s, j, k]:+.2f}{value}", fill=255)
            images.append(image)
    return images


def load_run(run_dir: Path, reward_from: str | None = None):
    """(config, variant, parameters, step, game, game parameters) of a run the probe can read:
    a controller variant's world model on the built-in game, with the reward head `reward_from`
    (`imagination_probe.reward_source`). ValueError naming what is missing otherwise."""
    from cdrl.models import make_variant
    from cdrl.runs.init_from import restore_params
    from cdrl.runs.rundir import RunDir
    from cdrl.runs.sources import run_game

    run = RunDir(run_dir)
    cfg = run.read_config()
    if cfg.kind == "model_free":
        raise ValueError(f"run {run_dir} trains {cfg.learner}, which has no world model to imagine with")
    if cfg.data != "game":
        raise ValueError(f"run {run_dir} trains on data {cfg.data!r}, not the built-in game the probe plays")
    variant = make_variant(cfg.variant, cfg.arch)
    try:
        ip.reward_source(variant, cfg.lookahead_hparams(), reward_from)
    except ValueError as exc:
        raise ValueError(f"run {run_dir}: {exc}") from None
    cfg, params, step = restore_params(run)
    game, env_params = run_game(cfg)
    return cfg, variant, params, step, game, env_params


def imagination_report(run_dir: Path, games: int = 32, every: int = 10, out: Path | None = None,
                       video: bool = True, reward_from: str | None = None) -> tuple[dict, list[Path]]:
    """The probe's figures of the run in `run_dir`, written as JSON to `out` (default
    RUN_DIR/imagination.json), and with `video` its GIF, RUN_DIR/imagination.gif. The imagined
    rewards come from `reward_from` (`imagination_probe.reward_source`). Returns the figures and
    the paths written."""
    run_dir = Path(run_dir)
    cfg, variant, params, step, game, env_params = load_run(run_dir, reward_from)
    hp = cfg.lookahead_hparams()
    max_steps = int(env_params.max_steps)
    figures = ip.probe(variant, params, game, env_params, hp, cfg.gamma, max_steps=max_steps, games=games,
                       every=every, reward_from=reward_from)
    if hp is not None:  # the value on the run's own held-out play, whose policy it was fitted to
        from cdrl.runs.rundir import RunDir
        from cdrl.runs.sources import load_episodes

        held_out = load_episodes(cfg, RunDir(run_dir).data_cache)[1]
        figures["value_corr_data"], figures["value_states_data"] = ip.data_value_corr(variant, params, hp, held_out,
                                                                                     cfg.gamma)
    result = {"run": str(run_dir), "variant": cfg.variant, "preset": cfg.preset, "level": cfg.level, "step": step,
              "games": games, "every": every, "horizon": ip.HORIZON, "explore": ip.EXPLORE, "gamma": cfg.gamma,
              "sequences": ip.SEQUENCES, "real_return": f"the plain sum of the real rewards over {ip.HORIZON} steps",
              **figures}
    out = Path(out) if out is not None else run_dir / "imagination.json"
    out.write_text(json.dumps(result, indent=1) + "\n")
    written = [out]
    if video:
        starts = max(1, min(WATCH_STARTS, max_steps // every - 1))
        watched = watch(variant, params, game, env_params, hp, starts=starts, every=every,
                        source=figures["reward_source"])
        written.append(write_gif(frame_images(watched, hp is not None), run_dir / "imagination.gif", FRAME_MS))
    return result, written


def summary(result: dict) -> str:
    """A few lines of the probe's figures: the ranking per horizon against always naming
    straight on, the reward AUC along straight on, and the value's correlation."""
    fmt = lambda x: "-" if x is None else f"{x:.3f}"  # noqa: E731
    lines = [f"imagination of {result['run']} ({result['variant']}, step {result['step']}): {result['starts']} starts, "
             f"the imagined reward from the {result['reward_source']}'s head",
             f"{'H':>4} {'agree':>7} {'straight':>9} {'corr_steer':>11} {'corr_all':>9}"]
    for h, row in result["by_horizon"].items():
        lines.append(f"{h:>4} {fmt(row['best_steer_agree']):>7} {fmt(row['always_straight_agree']):>9} "
                     f"{fmt(row['corr_steer']):>11} {fmt(row['corr_all']):>9}")
    aucs = result["reward_auc"]["straight"]
    shown = [k for k in (1, 5, 15) if k <= len(aucs)]
    lines.append(f"reward AUC along straight on at step {' / '.join(map(str, shown))}: "
                 f"{' / '.join(fmt(aucs[k - 1]) for k in shown)}")
    lines.append(f"value_corr: {fmt(result['value_corr'])} over {result['value_states']} followed states, "
                 f"{fmt(result.get('value_corr_data'))} over {result.get('value_states_data', 0)} of the run's held-out "
                 "play" if result["value_head"] else "value_corr: none (no value head)")
    return "\n".join(lines)
