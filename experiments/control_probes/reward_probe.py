"""Is the coming pellet in the frame, and in a world model's features?

Linear (ridge) probes for "a pellet is eaten on arriving at o_{t+1}" (the real reward r_{t+1} > 0)
on the episodes of a run's data set, fitted on its training episodes and scored by the AUC on
its held-out ones (0.5: chance):

- from the pixels around the player's head (the centre quarter of the frame; the view follows
  the head) and the action a_t, at the run's resolution and at the thesis's 150 x 150 (the same
  games, collected again at that size);
- from the world model's core output h_t (`Variant.features`, after the step that saw o_t and a_t);
- the model's own reward head r̃_{t+1}, as it is;

and, with the same inputs, ridge probes of the pellets the next 8 steps bring, Σ_k 0.9^k
max(r_{t+1+k}, 0) up to the episode's end (what steering needs: the pellets within reach, not only
the one at the mouth), scored by the held-out R²;

and, to say why a reward term shapes so little of the core, the norms of each loss term's
gradient (unweighted) per kernel at the run's initial parameters, on its first training chunk.

    .venv/bin/python experiments/control_probes/reward_probe.py RUN_DIR [--out FILE]

RUN_DIR: a controller variant's run (offline, `--controller none`, or online) whose data set
is the built-in game's. Ends with one JSON line.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

if not __package__:  # run as a file, not with -m: the repository root on the path (benchmarks/, experiments/)
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.common import emit  # noqa: E402

RIDGE = 10.0  # the probes' L2 penalty, on standardised inputs
AHEAD, AHEAD_GAMMA = 8, 0.9  # the pellets-ahead target: steps and discount


def auc(score: np.ndarray, positive: np.ndarray) -> float:
    """The probability that a positive step scores above a negative one (ties count half)."""
    pos, neg = score[positive], score[~positive]
    return float(np.mean(pos[:, None] > neg[None, :]) + 0.5 * np.mean(pos[:, None] == neg[None, :]))


def ridge_predict(x_train, y_train, x_test) -> np.ndarray:
    mu, sd = x_train.mean(0), x_train.std(0) + 1e-6
    a = np.c_[(x_train - mu) / sd, np.ones(len(x_train))]
    b = np.c_[(x_test - mu) / sd, np.ones(len(x_test))]
    return b @ np.linalg.solve(a.T @ a + RIDGE * np.eye(a.shape[1]), a.T @ y_train.astype(float))


def ridge_auc(x_train, y_train, x_test, y_test) -> float:
    return auc(ridge_predict(x_train, y_train, x_test), y_test)


def ridge_r2(x_train, y_train, x_test, y_test) -> float:
    """Held-out R² of the ridge fit (1 - residual / total sum of squares about the test mean)."""
    resid = y_test - ridge_predict(x_train, y_train, x_test)
    return float(1.0 - np.sum(resid ** 2) / np.sum((y_test - y_test.mean()) ** 2))


def pellets_ahead(rewards: np.ndarray, n: int) -> np.ndarray:
    """[n]: for each step t < n, Σ_{k < AHEAD} AHEAD_GAMMA^k max(r_{t+1+k}, 0), the rewards
    of the episode only (`rewards[j]` is r_j, received on arriving at o_j)."""
    pos = np.maximum(np.asarray(rewards[1:], np.float64), 0.0)
    out = np.zeros(len(pos))
    for k in range(min(AHEAD, len(pos))):
        out[: len(pos) - k] += AHEAD_GAMMA ** k * pos[k:]
    return out[:n]


def ahead_targets(episodes) -> np.ndarray:
    return np.concatenate([pellets_ahead(episodes[i].rewards, len(episodes[i].frames) - 1)
                           for i in range(len(episodes))])


def pixels(episodes):
    """(centre-quarter pixels of o_t with a_t, pellet eaten at t+1) over every step."""
    xs, ys = [], []
    for i in range(len(episodes)):
        ep = episodes[i]
        frames, n = np.asarray(ep.frames, np.float32) / 255.0, len(ep.frames) - 1
        size = frames.shape[1]
        lo, hi = size // 2 - size // 8, size // 2 + size // 8
        xs.append(np.c_[frames[:n, lo:hi, lo:hi].reshape(n, -1), ep.actions[:n]])
        ys.append(ep.rewards[1: n + 1] > 0)
    return np.concatenate(xs), np.concatenate(ys)


def model_outputs(variant, params, episodes):
    """(h_t, r̃_{t+1}) of the model teacher-forced on every episode, step by step."""
    import jax
    import jax.numpy as jnp

    from cdrl.models.base import StepInput

    @jax.jit
    def unroll(obs, action, first):
        def body(carry, x):
            carry, out = variant.step(params, carry, x)
            return carry, (variant.features(carry), out["reward"])
        return jax.lax.scan(body, variant.init_carry(1), StepInput(obs=obs, action=action, is_first=first))[1]

    hs, rs = [], []
    for i in range(len(episodes)):
        ep = episodes[i]
        n = len(ep.frames) - 1
        frames = jnp.asarray(np.asarray(ep.frames[:n, None], np.float32) / 255.0)
        h, r = unroll(frames, jnp.asarray(ep.actions[:n, None], jnp.float32), jnp.arange(n)[:, None] == 0)
        hs.append(np.asarray(h[:, 0]))
        rs.append(np.asarray(r[:, 0]))
    return np.concatenate(hs), np.concatenate(rs)


def term_gradients(variant, cfg, train) -> dict:
    """{kernel: {term: ||d term / d kernel||}} at the parameters `cfg` starts from, on the first
    chunk of its training stream, each term unweighted (the frame BCE is a mean over pixels)."""
    import jax
    import jax.numpy as jnp

    from cdrl.data.stream import ChunkStream
    from cdrl.training.step import chunk_loss, init_state

    hp = cfg.hparams(variant)
    state = init_state(variant, jax.random.PRNGKey(cfg.seed), cfg.batch, hp)
    chunk = ChunkStream(train, cfg.batch, cfg.unroll, image_size=cfg.arch.image_size,
                        action_dim=cfg.arch.action_dim, seed=cfg.seed).next_chunk()
    norms = {}
    for term in hp.loss_weights:
        only = hp.replace(loss_weights={k: jnp.float32(k == term) for k in hp.loss_weights})
        grads = jax.jit(jax.grad(lambda p: chunk_loss(variant, p, state.carry, only, chunk)[0]))(state.params)
        for path, g in jax.tree_util.tree_flatten_with_path(grads)[0]:
            if g.ndim >= 2:
                name = "/".join(str(getattr(k, "key", k)) for k in path)
                norms.setdefault(name, {})[term] = float(jnp.linalg.norm(g))
    return norms


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", help="a controller variant's run on the built-in game's data")
    parser.add_argument("--out", default=None, help="also write the JSON result to this file")
    args = parser.parse_args(argv)
    from cdrl.models import make_variant
    from cdrl.runs.init_from import restore_params
    from cdrl.runs.rundir import RunDir
    from cdrl.runs.sources import load_episodes

    run = RunDir(args.run_dir)
    cfg, params, step = restore_params(run)
    variant = make_variant(cfg.variant, cfg.arch)
    if not variant.predicts_reward or cfg.data != "game":
        raise SystemExit(f"{args.run_dir}: needs a reward variant's run on the built-in game's data")
    train, test = load_episodes(cfg, run.data_cache)
    result = {"run": str(run.path), "variant": cfg.variant, "preset": cfg.preset, "step": step, "ridge": RIDGE}
    (x_tr, y_tr), (x_te, y_te) = pixels(train), pixels(test)
    result["train_steps"], result["test_steps"] = len(y_tr), len(y_te)
    result["pellet_steps"] = {"train": int(y_tr.sum()), "test": int(y_te.sum())}
    result["auc_pixels"] = {cfg.preset: ridge_auc(x_tr, y_tr, x_te, y_te)}
    if cfg.preset != "thesis":
        big = dataclasses.replace(cfg, preset="thesis", obs_mean=0.0, obs_std=1.0)
        big_train, big_test = load_episodes(big, run.data_cache)
        result["auc_pixels"]["thesis"] = ridge_auc(*pixels(big_train), *pixels(big_test))
    (h_tr, _), (h_te, r_te) = model_outputs(variant, params, train), model_outputs(variant, params, test)
    result["auc_features"] = ridge_auc(h_tr, y_tr, h_te, y_te)
    result["auc_reward_head"] = auc(r_te, y_te)
    a_tr, a_te = ahead_targets(train), ahead_targets(test)
    result["pellets_ahead"] = {"steps": AHEAD, "gamma": AHEAD_GAMMA,
                               "r2_pixels": ridge_r2(x_tr, a_tr, x_te, a_te),
                               "r2_features": ridge_r2(h_tr, a_tr, h_te, a_te)}
    result["gradient_norms_at_init"] = term_gradients(variant, cfg, train)
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
