"""`--init-from RUN_DIR`: a run whose world model starts from another run's trained one.

The typical use is a world model learnt offline first, on recorded episodes of the game
(`--controller none`: a controller variant trained as the observation variants are,
teacher-forced on the recorded actions, its reward term off by default), then trained
further online while its controller learns (`--controller critic --init-from RUN_DIR`). The
source is any run of the same variant and preset, offline or online; its newest good
checkpoint's parameters replace the fresh ones (the optimiser's state starts afresh) and its
input normalisation (`obs_norm`, `obs_mean`, `obs_std`) and action size are taken over, since
the encoder learnt on them.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from cdrl.models import make_variant
from cdrl.runs.config import RunConfig
from cdrl.runs.online import build_learner
from cdrl.runs.rundir import RunDir
from cdrl.training import lookahead
from cdrl.training.step import init_state

ADOPTED = ("obs_norm", "obs_mean", "obs_std", "action_dim")  # what the encoder learnt on


def restore_params(run: RunDir) -> tuple[RunConfig, Any, int]:
    """(config, the world model's parameters, step) of the newest good checkpoint of `run`,
    an offline run or a controller run (PPO holds no world model). FileNotFoundError if it
    has no checkpoint; `cdrl.runs.checkpoint.CheckpointError` if every one is corrupt."""
    cfg = run.read_config()
    ckpts = run.read_checkpoints()
    if not ckpts.steps():
        raise FileNotFoundError(f"{run.checkpoint_dir} holds no checkpoint")
    if cfg.kind == "model_free":
        raise ValueError(f"run {run.path} trains {cfg.learner}, which has no world model")
    # The abstract shape of a state is all a restore needs; tracing it is much cheaper than
    # initialising one eagerly.
    if cfg.kind == "online":
        program = build_learner(cfg)
        like = jax.eval_shape(lambda: program.init(jax.random.PRNGKey(cfg.seed)))
    else:
        variant = make_variant(cfg.variant, cfg.arch)
        like = jax.eval_shape(lambda: init_state(variant, jax.random.PRNGKey(0), cfg.batch, cfg.hparams(variant)))
    state, meta = ckpts.restore_newest(like)
    return cfg, (program.world_model(state) if cfg.kind == "online" else state.params), int(meta["step"])


def source_of(cfg: RunConfig) -> tuple[RunConfig, Any] | None:
    """For a new run of `cfg` with `init_from`: (`cfg` with the source's input normalisation
    and action size, the source's world-model parameters), after checking that they are the
    parameters of the model `cfg` trains. None without `init_from`."""
    if not cfg.init_from:
        return None
    where = f"init_from {cfg.init_from}"
    if cfg.kind == "model_free":
        raise ValueError(f"{where}: {cfg.learner} has no world model to start from another run's")
    source = RunDir(cfg.init_from)
    try:
        src, params, _ = restore_params(source)
    except (FileNotFoundError, ValueError) as exc:
        raise ValueError(f"{where}: {exc}") from None
    for name in ("variant", "preset", "max_filter"):
        if getattr(src, name) != getattr(cfg, name):
            raise ValueError(f"{where}: its run trains {name} {getattr(src, name)!r}, this one {getattr(cfg, name)!r}; "
                             "a world model starts only from one of the same variant and preset")
    adopted = dataclasses.replace(cfg, **{name: getattr(src, name) for name in ADOPTED})
    variant, heads = make_variant(cfg.variant, adopted.arch), cfg.lookahead_hparams()
    params = fit_heads(variant, params, heads, jax.random.PRNGKey(cfg.seed))
    like = jax.eval_shape(lambda k: lookahead.with_heads(variant, variant.init(k), k, heads), jax.random.PRNGKey(0))
    if jax.tree_util.tree_structure(params) != jax.tree_util.tree_structure(like):
        raise ValueError(f"{where}: its parameters are not those of this run's model")
    for (path, got), want in zip(jax.tree_util.tree_leaves_with_path(params), jax.tree.leaves(like)):
        if got.shape != want.shape:
            raise ValueError(f"{where}: parameter {jax.tree_util.keystr(path)} has shape {got.shape}, this run's "
                             f"model {want.shape}")
    return adopted, params


def fit_heads(variant, params, heads, key):
    """The source's parameters with the look-ahead heads this run trains: the source's own where
    it trained heads of the same shape, fresh ones from `key` where it trained none or others,
    none where this run trains none (`heads` None)."""
    model = {k: v for k, v in params.items() if k != "lookahead"}
    if heads is None:
        return model
    fresh = lookahead.with_heads(variant, model, key, heads)
    if "lookahead" in params and jax.tree.map(jnp.shape, params["lookahead"]) == jax.tree.map(jnp.shape,
                                                                                               fresh["lookahead"]):
        return params
    return fresh
