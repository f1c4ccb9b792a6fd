"""Can a memoryless network steer from the frames? Behaviour cloning of the privileged policy.

The privileged policy (`envs.policies.privileged_policy`) plays `--games` training games (seeds
0, 1, ...; a fifth of its steps replaced by random turns, so that the data holds recoveries);
PPO's network (`cdrl.learners.ppo`: the small preset's observation encoder, a SELU torso, one
logit a button; the frames standardised by their mean and deviation) learns its buttons from
the frame it chose them on, by the per-button BCE (Adam, `--lr`, minibatches of `--batch`).
Every `--eval-every` updates the network plays, pressing a button where its logit is above 0,
the control experiment's 64 held-out games (`cdrl.evaluation.play`, seeds 10000-10063, at most
200 steps), beside never-accelerate and the privileged policy at the end.

With `--augment d4` every minibatch frame is turned by a random quarter turn and mirrored half
the time, its turn buttons swapped where mirrored (`envs.symmetry`: the north-up game's
symmetries); the network then also plays symmetrised (its logits averaged over the eight
transforms of each frame, mapped back: exactly invariant). `--camera heading` plays the level
with the camera that turns with the player (level `turned-true-visible` is `visible` seen so; this
gives the same camera with the level's own pellets).

It measures how much of the steering a pixel policy of this size can learn with the answers
given, which bounds what reinforcement from the same frames can reach.

With `--turn read-heading` the frames are first turned so that the player's heading points up the
screen, by the heading a second network of the same kind reads off each frame (trained first, as
`--target heading`, for `--heading-updates`); the cloned policy learns and plays on the turned
frames (the heading read from the pixels at play too): a north-up policy with the turn to its
heading built in.

With `--target heading` the same network instead learns the player's heading (cos, sin; MSE on
the logits of two buttons scaled by 10, as the policy head starts 100 times smaller) from the
same frames, and is scored on the frames of 32 other privileged games (seeds 5000-5031): R² of
(cos, sin) and the median and 90th percentile of the angle's error. It asks whether the frame
shows the heading that a north-up policy must read before it steers.

    .venv/bin/python experiments/control_probes/imitation_probe.py [--level thesis] [--camera north] [--augment d4]
        [--target buttons|heading] [--turn read-heading] [--out FILE]

Ends with one JSON line.
"""
from __future__ import annotations

import argparse
import dataclasses
import functools
import sys
import time
from pathlib import Path

if not __package__:  # run as a file, not with -m: the repository root on the path (benchmarks/, experiments/)
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import emit  # noqa: E402

EXPLORE = 0.2  # the share of the privileged policy's steps replaced by random turns


def collect(game, env_params, games: int, steps: int, size: int, first_seed: int = 0):
    """Frames `[N, size, size]` of the privileged games' live steps (seeds `first_seed`, ...),
    the buttons the privileged policy chose on each `[N, 3]` (executed or not) and the player's
    heading `[N]`."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from cdrl.data.frames import resize_obs
    from envs.policies import privileged_policy, random_turns_instead

    privileged = privileged_policy(game)

    @jax.jit
    def run(keys):
        def one(key):
            k_reset, k_run = jax.random.split(key)
            obs, state = game.reset(k_reset, env_params)

            def body(c, _):
                state, obs, key, alive = c
                key, k_policy, k_explore, k_env = jax.random.split(key, 4)
                label, _ = privileged.step(k_policy, None, obs, state, env_params)
                executed = random_turns_instead(k_explore, label, EXPLORE)
                frame, heading = resize_obs(obs, size), state.heading[0]
                obs, state, _, term, trunc, _ = game.step(k_env, state, executed, env_params)
                return (state, obs, key, alive & ~(term | trunc)), (frame, label, heading, alive)

            return jax.lax.scan(body, (state, obs, k_run, jnp.array(True)), None, length=steps)[1]

        return jax.vmap(one)(keys)

    keys = jax.vmap(jax.random.PRNGKey)(first_seed + jnp.arange(games))
    frames, labels, heading, alive = (np.asarray(x) for x in run(keys))
    on = alive.reshape(-1)
    return frames.reshape(-1, size, size)[on], labels.reshape(-1, 3)[on], heading.reshape(-1)[on]


HEADING_SCALE = 10.0  # the policy head's kernel starts at 0.01 of its usual scale
HEADING_TEST_SEED = 5000


def heading_scores(predicted, heading):
    """R² of (cos, sin) and the median / 90th percentile of the angle's absolute error (degrees)."""
    import numpy as np

    target = np.stack([np.cos(heading), np.sin(heading)], axis=1)
    r2 = 1.0 - np.sum((predicted - target) ** 2) / np.sum((target - target.mean(0)) ** 2)
    error = np.degrees(np.abs(np.angle(np.exp(1j * (np.arctan2(predicted[:, 1], predicted[:, 0]) - heading)))))
    return {"r2": float(r2), "median_error_deg": float(np.median(error)),
            "p90_error_deg": float(np.percentile(error, 90))}


def heading_of(arch, params, frames):
    """The heading network's (cos, sin) of frames `[N, S, S]`."""
    from cdrl.learners import ppo

    return HEADING_SCALE * ppo.policy_value(arch, params, frames)[0][..., :2]


@functools.lru_cache(maxsize=4)
def turned_policy(arch):
    """(init, step) for `play` with params (heading network, policy): the frame turned by the
    heading read off it, then the policy's buttons (one pair per architecture, so every
    evaluation reuses one compiled program)."""
    import jax.numpy as jnp

    from cdrl.data.frames import resize_obs
    from cdrl.learners import ppo
    from envs import symmetry

    def init(key, params):
        del key, params
        return jnp.zeros((), jnp.float32)

    def step(key, state, obs, params):
        del key
        frame = resize_obs(obs, arch.image_size)[None]
        turned = symmetry.turn_to_heading(frame, heading_of(arch, params[0], frame))
        logits, _ = ppo.policy_value(arch, params[1], turned)
        return (logits[0] > 0.0).astype(jnp.float32), state

    return init, step


@functools.lru_cache(maxsize=4)
def symmetrised_policy(arch):
    """(init, step) for `play`: the network's logits averaged over the eight symmetric views (one
    pair per architecture)."""
    import jax.numpy as jnp

    from cdrl.data.frames import resize_obs
    from cdrl.learners import ppo
    from envs import symmetry

    def init(key, params):
        del key, params
        return jnp.zeros((), jnp.float32)

    def step(key, state, obs, params):
        del key
        logits, _ = ppo.policy_value(arch, params, symmetry.all_transforms(resize_obs(obs, arch.image_size)))
        return (symmetry.symmetrised_logits(logits) > 0.0).astype(jnp.float32), state

    return init, step


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--level", default="thesis", help="the game's level (default: thesis)")
    parser.add_argument("--camera", default=None, choices=("north", "heading"),
                        help="override the level's camera (default: the level's own)")
    parser.add_argument("--augment", default="none", choices=("none", "d4"), help="minibatch augmentation")
    parser.add_argument("--target", default="buttons", choices=("buttons", "heading"),
                        help="what the network learns: the privileged buttons, or the player's heading")
    parser.add_argument("--turn", default="none", choices=("none", "read-heading"),
                        help="turn every frame so that the heading read off it points up (default: none)")
    parser.add_argument("--heading-updates", type=int, default=4000,
                        help="--turn read-heading: updates of the heading network (default 4000)")
    parser.add_argument("--games", type=int, default=256, help="privileged training games (default 256)")
    parser.add_argument("--steps", type=int, default=200, help="steps a training game (default 200)")
    parser.add_argument("--updates", type=int, default=8000, help="Adam updates (default 8000)")
    parser.add_argument("--eval-every", type=int, default=2000, help="updates between evaluations (default 2000)")
    parser.add_argument("--batch", type=int, default=128, help="minibatch size (default 128)")
    parser.add_argument("--lr", type=float, default=1e-3, help="Adam's learning rate (default 1e-3)")
    parser.add_argument("--seed", type=int, default=0, help="the network's initialisation and minibatches")
    parser.add_argument("--out", default=None, help="also write the JSON result to this file")
    args = parser.parse_args(argv)
    if args.target == "heading" and args.augment != "none":
        parser.error("--target heading takes no --augment (a turned frame shows another heading)")
    if args.turn != "none" and (args.target != "buttons" or args.augment != "none"):
        parser.error("--turn read-heading is for --target buttons without --augment")
    if args.updates % args.eval_every:
        parser.error(f"--updates ({args.updates}) must be a multiple of --eval-every ({args.eval_every})")

    import jax
    import jax.numpy as jnp
    import numpy as np
    import optax

    from cdrl.evaluation.play import EVAL_SEED, compare_policies
    from cdrl.models.arch import PRESETS
    from cdrl.learners import ppo
    from envs import symmetry
    from envs.slither import LEVEL_GAMES, Slither, canonical_level, level_game, level_params

    game = level_game(args.level)
    if args.camera is not None:
        game = Slither(**{**LEVEL_GAMES.get(canonical_level(args.level), {}), "camera": args.camera})
    env_params = level_params(args.level)
    arch = PRESETS["small"]
    start = time.time()
    frames, labels, heading = collect(game, env_params, args.games, args.steps, arch.image_size)
    arch = dataclasses.replace(arch, obs_mean=float(frames.mean()), obs_std=float(frames.std()))
    if args.target == "heading":
        labels = np.stack([np.cos(heading), np.sin(heading)], axis=1)
        test_frames, _, test_heading = collect(game, env_params, 32, args.steps, arch.image_size, HEADING_TEST_SEED)
    frames, labels = jnp.asarray(frames), jnp.asarray(labels)
    collect_s = time.time() - start

    opt = optax.adam(args.lr)

    def heading_loss(params, x, y):
        return jnp.mean(jnp.square(heading_of(arch, params, x) - y))

    def buttons_loss(params, x, y):
        logits, _ = ppo.policy_value(arch, params, x)
        return optax.sigmoid_binary_cross_entropy(logits, y).mean()

    def trainer(frames, labels, loss_fn, steps):
        """A jitted `steps` Adam updates on random minibatches of (frames, labels)."""
        @jax.jit
        def train(params, opt_state, key):
            def body(c, k):
                params, opt_state = c
                k_draw, k_aug = jax.random.split(k)
                idx = jax.random.randint(k_draw, (args.batch,), 0, frames.shape[0])
                x, y = frames[idx], labels[idx]
                if args.augment == "d4":
                    x, y = symmetry.augment(k_aug, x, y)
                loss, grads = jax.value_and_grad(loss_fn)(params, x, y)
                updates, opt_state = opt.update(grads, opt_state, params)
                return (optax.apply_updates(params, updates), opt_state), loss

            (params, opt_state), losses = jax.lax.scan(body, (params, opt_state), jax.random.split(key, steps))
            return params, opt_state, jnp.mean(losses)

        return train

    read = jax.jit(functools.partial(heading_of, arch))
    if args.turn == "read-heading":
        xy = jnp.asarray(np.stack([np.cos(heading), np.sin(heading)], axis=1))
        reader = ppo.init_params(arch, jax.random.PRNGKey(500 + args.seed))
        reader, _, reader_loss = trainer(frames, xy, heading_loss, args.heading_updates)(
            reader, opt.init(reader), jax.random.PRNGKey(2000 + args.seed))
        frames = jnp.concatenate([symmetry.turn_to_heading(frames[i:i + 512], read(reader, frames[i:i + 512]))
                                  for i in range(0, frames.shape[0], 512)])
    params = ppo.init_params(arch, jax.random.PRNGKey(args.seed))
    opt_state = opt.init(params)
    train = trainer(frames, labels, heading_loss if args.target == "heading" else buttons_loss, args.eval_every)

    key = jax.random.PRNGKey(1000 + args.seed)
    curve = []
    for done in range(args.eval_every, args.updates + 1, args.eval_every):
        key, k = jax.random.split(key)
        params, opt_state, loss = train(params, opt_state, k)
        if args.target == "heading":
            predicted = np.concatenate([np.asarray(read(params, test_frames[i:i + 512]))
                                        for i in range(0, len(test_frames), 512)])
            point = {"updates": done, "train_mse": float(loss), **heading_scores(predicted, test_heading)}
            print(point, flush=True)
            curve.append(point)
            continue
        if args.turn == "read-heading":
            policies = {"cloned_turned": (*turned_policy(arch), (reader, params))}
        else:
            policies = {"cloned": ppo.ppo_policy(arch, params)}
        if args.augment == "d4":
            policies["cloned_symmetrised"] = (*symmetrised_policy(arch), params)
        last = done == args.updates
        rows = compare_policies(game, env_params, policies, 64, 200, seed=EVAL_SEED, references=last)
        point = {"updates": done, "train_bce": float(loss),
                 **{name: round(row["mean_return"], 3) for name, row in rows.items() if name in policies}}
        print(point, flush=True)
        curve.append(point)
    result = {"level": args.level, "camera": game.spec.camera, "target": args.target, "augment": args.augment,
              "games": args.games, "frames": int(frames.shape[0]), "updates": args.updates, "batch": args.batch,
              "lr": args.lr, "seed": args.seed, "collect_s": round(collect_s, 1),
              "seconds": round(time.time() - start, 1), "curve": curve}
    if args.turn == "read-heading":
        result.update(turn=args.turn, heading_updates=args.heading_updates, heading_train_mse=float(reader_loss))
    if args.target == "heading":
        result["held_out_frames"] = int(len(test_frames))
    else:
        result["turn_rates"] = [float(r) for r in labels.mean(0)]
        result["held_out"] = rows
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
