"""What a run's config points to: its episodes (a data set directory, the built-in game's
data collected and cached, or synthetic episodes) and, for controller runs, the game."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from cdrl.data import store, synthetic
from cdrl.models import make_variant
from cdrl.runs.config import RunConfig


def load_episodes(cfg: RunConfig, cache_root: Path):
    """(train, test) episode sources for the run."""
    size = cfg.arch.image_size
    uses_action = make_variant(cfg.variant, cfg.arch).uses_action
    if cfg.data == "synthetic":
        n_test = max(1, cfg.episodes // 10)
        train = synthetic.synthetic_episodes(cfg.episodes - n_test, cfg.episode_steps, size, cfg.seed, pushed=uses_action)
        test = synthetic.synthetic_episodes(n_test, cfg.episode_steps, size, cfg.seed + 10_000, pushed=uses_action)
        return train, test
    if cfg.data == "game":
        policy = "uniform" if uses_action else "behaviour"
        path = cache_root / f"slither-{policy}-{size}px-{cfg.episodes}ep-{cfg.episode_steps}steps-seed{cfg.seed}"
        store.collect(path, cfg.episodes, policy=policy, seed=cfg.seed, max_steps=cfg.episode_steps, obs_size=size)
    else:
        path = Path(cfg.data)
    return store.EpisodeDataset(path, split="train"), store.EpisodeDataset(path, split="test")


def make_game(spec: str):
    """The built-in game and its parameters, with `spec` ('name=value,...') overriding defaults."""
    from envs.slither import Slither

    game = Slither()
    params = game.default_params
    if spec:
        names = {f.name for f in dataclasses.fields(params)}
        changes = {}
        for item in spec.split(","):
            name, sep, value = item.partition("=")
            name = name.strip()
            if not sep or name not in names:
                raise ValueError(f"bad game parameter {item!r}; use name=value with a name out of {sorted(names)}")
            changes[name] = np.asarray(float(value), np.asarray(getattr(params, name)).dtype)
        params = params.replace(**changes)
    return game, params


def run_game(cfg: RunConfig):
    """The game a controller run plays: `cfg.env` over the defaults, episodes capped at
    `cfg.episode_steps` unless `cfg.env` sets `max_steps`."""
    game, params = make_game(cfg.env)
    if "max_steps" not in cfg.env:
        params = params.replace(max_steps=np.asarray(cfg.episode_steps, np.int32))
    return game, params
