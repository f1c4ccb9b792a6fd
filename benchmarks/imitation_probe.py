"""Can a memoryless network steer from the frames? Behaviour cloning of the privileged policy.

The privileged policy (`envs.policies.privileged_policy`) plays `--games` training games (seeds
0, 1, ...; a fifth of its steps replaced by random turns, so that the data holds recoveries);
PPO's network (`cdrl.training.ppo`: the small preset's observation encoder, a SELU torso, one
logit a button; the frames standardised by their mean and deviation) learns its buttons from
the frame it chose them on, by the per-button BCE (Adam, `--lr`, minibatches of `--batch`).
Every `--eval-every` updates the network plays, pressing a button where its logit is above 0,
the control experiment's 64 held-out games (`cdrl.evaluation.play`, seeds 10000-10063, at most
200 steps), beside never-accelerate and the privileged policy at the end.

With `--augment d4` every minibatch frame is turned by a random quarter turn and mirrored half
the time, its turn buttons swapped where mirrored (`envs.symmetry`: the north-up game's
symmetries); the network then also plays symmetrised (its logits averaged over the eight
transforms of each frame, mapped back: exactly invariant). `--camera heading` plays the level
with the camera that turns with the player (the `heading` level is `visible` seen so; this
gives the same camera with the level's own pellets).

It measures how much of the steering a pixel policy of this size can learn with the answers
given, which bounds what reinforcement from the same frames can reach.

    .venv/bin/python benchmarks/imitation_probe.py [--level thesis] [--camera north] [--augment d4] [--out FILE]

Ends with one JSON line.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time

from common import emit

EXPLORE = 0.2  # the share of the privileged policy's steps replaced by random turns


def collect(game, env_params, games: int, steps: int, size: int):
    """Frames `[N, size, size]` of the privileged games' live steps and the buttons the
    privileged policy chose on each `[N, 3]` (executed or not)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from cdrl.data.frames import resize_obs
    from envs.policies import privileged_policy

    privileged = privileged_policy(game)

    @jax.jit
    def run(keys):
        def one(key):
            k_reset, k_run = jax.random.split(key)
            obs, state = game.reset(k_reset, env_params)

            def body(c, _):
                state, obs, key, alive = c
                key, k_policy, k_turn, k_explore, k_env = jax.random.split(key, 5)
                label, _ = privileged.step(k_policy, None, obs, state, env_params)
                turns = (jax.random.uniform(k_turn, (3,)) < 0.5).astype(jnp.float32) * jnp.array([1.0, 1.0, 0.0])
                executed = jnp.where(jax.random.uniform(k_explore) < EXPLORE, turns, label)
                frame = resize_obs(obs, size)
                obs, state, _, term, trunc, _ = game.step(k_env, state, executed, env_params)
                return (state, obs, key, alive & ~(term | trunc)), (frame, label, alive)

            return jax.lax.scan(body, (state, obs, k_run, jnp.array(True)), None, length=steps)[1]

        return jax.vmap(one)(keys)

    frames, labels, alive = (np.asarray(x) for x in run(jax.vmap(jax.random.PRNGKey)(jnp.arange(games))))
    on = alive.reshape(-1)
    return frames.reshape(-1, size, size)[on], labels.reshape(-1, 3)[on]


def symmetrised_policy(arch):
    """(init, step) for `play`: the network's logits averaged over the eight symmetric views."""
    import jax.numpy as jnp

    from cdrl.data.frames import resize_obs
    from cdrl.training import ppo
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
    parser.add_argument("--games", type=int, default=256, help="privileged training games (default 256)")
    parser.add_argument("--steps", type=int, default=200, help="steps a training game (default 200)")
    parser.add_argument("--updates", type=int, default=8000, help="Adam updates (default 8000)")
    parser.add_argument("--eval-every", type=int, default=2000, help="updates between evaluations (default 2000)")
    parser.add_argument("--batch", type=int, default=128, help="minibatch size (default 128)")
    parser.add_argument("--lr", type=float, default=1e-3, help="Adam's learning rate (default 1e-3)")
    parser.add_argument("--seed", type=int, default=0, help="the network's initialisation and minibatches")
    parser.add_argument("--out", default=None, help="also write the JSON result to this file")
    args = parser.parse_args(argv)
    if args.updates % args.eval_every:
        parser.error(f"--updates ({args.updates}) must be a multiple of --eval-every ({args.eval_every})")

    import jax
    import jax.numpy as jnp
    import optax

    from cdrl.evaluation.play import EVAL_SEED, compare_policies
    from cdrl.models.arch import PRESETS
    from cdrl.training import ppo
    from envs import symmetry
    from envs.slither import LEVEL_GAMES, Slither, level_game, level_params

    game = level_game(args.level)
    if args.camera is not None:
        game = Slither(**{**LEVEL_GAMES.get(args.level, {}), "camera": args.camera})
    env_params = level_params(args.level)
    arch = PRESETS["small"]
    start = time.time()
    frames, labels = collect(game, env_params, args.games, args.steps, arch.image_size)
    arch = dataclasses.replace(arch, obs_mean=float(frames.mean()), obs_std=float(frames.std()))
    frames, labels = jnp.asarray(frames), jnp.asarray(labels)
    collect_s = time.time() - start

    opt = optax.adam(args.lr)
    params = ppo.init_params(arch, jax.random.PRNGKey(args.seed))
    opt_state = opt.init(params)

    def loss_fn(params, x, y):
        logits, _ = ppo.policy_value(arch, params, x)
        return optax.sigmoid_binary_cross_entropy(logits, y).mean()

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

        (params, opt_state), losses = jax.lax.scan(body, (params, opt_state), jax.random.split(key, args.eval_every))
        return params, opt_state, jnp.mean(losses)

    key = jax.random.PRNGKey(1000 + args.seed)
    curve = []
    for done in range(args.eval_every, args.updates + 1, args.eval_every):
        key, k = jax.random.split(key)
        params, opt_state, loss = train(params, opt_state, k)
        policies = {"cloned": ppo.ppo_policy(arch, params)}
        if args.augment == "d4":
            policies["cloned_symmetrised"] = (*symmetrised_policy(arch), params)
        last = done == args.updates
        rows = compare_policies(game, env_params, policies, 64, 200, seed=EVAL_SEED, references=last)
        point = {"updates": done, "train_bce": float(loss),
                 **{name: round(row["mean_return"], 3) for name, row in rows.items() if name in policies}}
        print(point, flush=True)
        curve.append(point)
    result = {"level": args.level, "camera": game.spec.camera, "augment": args.augment, "games": args.games,
              "frames": int(frames.shape[0]), "turn_rates": [float(r) for r in labels.mean(0)],
              "updates": args.updates, "batch": args.batch, "lr": args.lr, "seed": args.seed,
              "collect_s": round(collect_s, 1), "seconds": round(time.time() - start, 1), "curve": curve,
              "held_out": rows}
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
