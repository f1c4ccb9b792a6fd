"""`cdrl eval --policy RUN_DIR --video`: a game of a run's learned policy you can watch.

`record` plays one game as `cdrl.evaluation.play.play` plays it (the same keys, so the same
game and return for the same seed) and keeps every step: the game's screen, the view the
policy sees, the buttons it pressed and the reward. A policy that reports its plans (the
planner's state holds `scores`, one per button combination) has them kept too. `frame_images`
draws each step; `cdrl.analysis.animation.write_gif` writes the GIF.
"""
from __future__ import annotations

import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from cdrl.analysis.animation import write_gif
from cdrl.data.frames import model_obs
from cdrl.evaluation.play import TEST_SEED

VIEW = 150  # the side the view is drawn at
SCREEN_SHRINK = 2  # the raw screen (500 x 300) is drawn at half size
PANEL = 190  # the width of the text beside the frames
HEADER = 14
PAD = 4
FRAME_MS = 100
BUTTONS = ("right", "left", "accel")


@functools.partial(jax.jit, static_argnums=(0, 1, 2, 4, 5))
def _record(game, policy_init, policy_step, env_params, max_steps: int, arch, key, params):
    k_reset, k_policy, k_run = jax.random.split(key, 3)
    obs, env_state = game.reset(k_reset, env_params)

    def body(c, _):
        env_state, obs, pstate, key = c
        key, k_act, k_env = jax.random.split(key, 3)
        action, pstate = policy_step(k_act, pstate, obs, params)
        seen = {"screen": game.render_raw(env_state, env_params),
                "view": model_obs(obs, arch) if arch is not None else obs, "action": action,
                "scores": pstate["scores"][0] if isinstance(pstate, dict) and "scores" in pstate else jnp.zeros(0)}
        obs, env_state, reward, term, trunc, _ = game.step(k_env, env_state, action, env_params)
        return (env_state, obs, pstate, key), {**seen, "reward": reward, "done": term | trunc}

    c0 = (env_state, obs, policy_init(k_policy, params=params), k_run)
    return jax.lax.scan(body, c0, None, length=max_steps)[1]


def record(game, env_params, policy: tuple, seed: int, max_steps: int, arch=None) -> dict:
    """One game of the learned `policy` (`(init, step, params)`, as `controller_policy` gives
    it) on game seed `seed`, up to its first end or `max_steps`: per step the screen `[T, 300,
    500, 3]` uint8, the view `[T, S, S]` (after the model's max filter for `arch`), the buttons
    `[T, 3]`, the reward `[T]` and the plans' scores `[T, C]` (C = 0 for a policy without
    plans), as NumPy arrays; `return` and `length` as `play` counts them."""
    init, step, params = policy
    steps = _record(game, init, step, env_params, int(max_steps), arch, jax.random.PRNGKey(seed), params)
    steps = jax.tree.map(np.asarray, steps)
    done = np.flatnonzero(steps["done"])
    length = int(done[0]) + 1 if done.size else int(max_steps)
    kept = {k: v[:length] for k, v in steps.items() if k != "done"}
    return {**kept, "return": float(np.sum(kept["reward"])), "length": length}


def combo_names(count: int) -> list[str]:
    """The button combinations' short names, in `BUTTON_COMBOS` order: R, L, A or '.' each."""
    from cdrl.models.base import BUTTON_COMBOS

    return ["".join(c if on else "." for c, on in zip("RLA", combo)) for combo in BUTTON_COMBOS[:count]]


def frame_images(game_record: dict, title: str = "") -> list:
    """One RGB PIL image per step: the screen, the view the policy sees, and beside them the
    step, the reward so far, the buttons pressed and, for a planner, each plan's score."""
    from PIL import Image, ImageDraw

    screen_h, screen_w = game_record["screen"].shape[1:3]
    sw, sh = screen_w // SCREEN_SHRINK, screen_h // SCREEN_SHRINK
    height = HEADER + max(sh, VIEW) + PAD
    width = sw + VIEW + PANEL + 4 * PAD
    scores = game_record["scores"]
    names = combo_names(scores.shape[1]) if scores.shape[1] else []
    total = 0.0
    images = []
    for t in range(game_record["length"]):
        total += float(game_record["reward"][t])
        image = Image.new("RGB", (width, height), (0, 0, 0))
        draw = ImageDraw.Draw(image)
        draw.text((PAD, 1), f"{title} step {t + 1}/{game_record['length']}: screen | the policy's view", fill="white")
        screen = Image.fromarray(game_record["screen"][t]).resize((sw, sh))
        view = Image.fromarray((np.clip(game_record["view"][t], 0.0, 1.0) * 255).astype(np.uint8)).resize((VIEW, VIEW))
        image.paste(screen, (PAD, HEADER))
        image.paste(view.convert("RGB"), (2 * PAD + sw, HEADER))
        x, y = 3 * PAD + sw + VIEW, HEADER
        draw.text((x, y), f"reward {game_record['reward'][t]:+.2f}", fill="white")
        draw.text((x, y + 12), f"return {total:+.2f}", fill="white")
        for i, name in enumerate(BUTTONS):
            on = game_record["action"][t, i] > 0.5
            box = (x + i * 60, y + 28, x + i * 60 + 54, y + 42)
            draw.rectangle(box, fill=(255, 200, 0) if on else (60, 60, 60))
            draw.text((box[0] + 3, box[1] + 1), name, fill="black" if on else "white")
        if names:
            draw.text((x, y + 48), "plans (next buttons):", fill="white")
            row = scores[t]
            low, high = float(row.min()), float(row.max())
            for j, (name, s) in enumerate(zip(names, row)):
                top = y + 60 + 11 * j
                share = 0.0 if high == low else (float(s) - low) / (high - low)
                colour = (255, 200, 0) if j == int(np.argmax(row)) else (120, 160, 255)
                draw.rectangle((x + 30, top + 2, x + 30 + int(90 * share) + 1, top + 9), fill=colour)
                draw.text((x, top), name, fill="white")
                draw.text((x + 125, top), f"{s:+.3f}", fill="white")
        images.append(image)
    return images


def policy_video(game, env_params, policy: tuple, seed: int, max_steps: int, path: Path, arch=None,
                 title: str = "") -> dict:
    """Record one game (`record`) and write it to `path` as an animated GIF; returns the record."""
    game_record = record(game, env_params, policy, seed, max_steps, arch)
    write_gif(frame_images(game_record, title), path, FRAME_MS)
    return game_record


def policy_run_video(run_dir: Path, seed: int = TEST_SEED) -> Path:
    """`cdrl eval --policy RUN_DIR --video`: one game (seed `seed`) of the run's learned policy,
    noise-free (its latest good checkpoint), as RUN_DIR/policy.gif. Returns its path."""
    from cdrl.runs.online import restore_learner
    from cdrl.runs.rundir import RunDir

    run = RunDir(run_dir)
    cfg, learner, state = restore_learner(run)
    path = run.path / "policy.gif"
    policy_video(learner.game, learner.env_params, learner.policy(state), seed, cfg.episode_steps, path,
                 arch=learner.arch, title=f"{learner.name} game {seed}")
    return path
