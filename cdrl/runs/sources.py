"""What a run's config points to: its episodes (a data set directory, the built-in game's
data collected and cached, or synthetic episodes), the game of controller runs, and the
frame statistics that `obs_norm data` standardises the encoder's input with."""
from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Sequence

import numpy as np

from cdrl.data import store, synthetic
from cdrl.data.collect import collect
from cdrl.data.episode import Episode
from cdrl.models import make_variant
from cdrl.runs.config import RunConfig


def game_params(cfg: RunConfig):
    """The built-in game's parameters of a run: its level, then `cfg.env` ('name=value,...')."""
    from envs.slither import SlitherParams, canonical_params, level_params

    params = level_params(cfg.level)
    if cfg.env:
        names = {f.name for f in dataclasses.fields(SlitherParams)}
        changes = {}
        for item in cfg.env.split(","):
            name, sep, value = item.partition("=")
            name = name.strip()
            if not sep or name not in names:
                raise ValueError(f"bad game parameter {item!r}; use name=value with a name out of {sorted(names)}")
            try:
                changes[name] = np.asarray(float(value), np.asarray(getattr(params, name)).dtype)
            except ValueError:
                raise ValueError(f"bad game parameter {item!r}: {value!r} is not a number") from None
        params = canonical_params(params.replace(**changes))
    return params


def _cache_name(cfg: RunConfig, policy: str, episodes: int) -> str:
    game = f"-{cfg.level}" if cfg.level != "thesis" else ""
    if cfg.env:
        game += "-" + re.sub(r"[^A-Za-z0-9.=_-]+", "_", cfg.env.replace(",", "_"))
    view = f"-max{cfg.arch.max_filter}" if cfg.arch.max_filter > 1 else ""
    return (f"slither-{policy}-{cfg.arch.image_size}px{view}-{episodes}ep-{cfg.episode_steps}steps-seed{cfg.seed}"
            f"{game}")


def data_policy(cfg: RunConfig) -> str:
    """The policy that plays the run's built-in-game data: `cfg.data_policy`, or for 'auto' the
    thesis's choice (uniform buttons for a variant that takes actions, else behaviour switching)."""
    if cfg.data_policy != "auto":
        return cfg.data_policy
    return "uniform" if make_variant(cfg.variant, cfg.arch).uses_action else "behaviour"


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
        from envs.slither import LEVEL_GAMES

        policy = data_policy(cfg)
        path = cache_root / _cache_name(cfg, policy, cfg.episodes)
        collect(path, cfg.episodes, policy=policy, seed=cfg.seed, max_steps=cfg.episode_steps, obs_size=size,
                max_filter=cfg.arch.max_filter, env_params=game_params(cfg), game_kwargs=LEVEL_GAMES.get(cfg.level, {}))
    else:
        path = Path(cfg.data)
    return store.EpisodeDataset(path, split="train"), store.EpisodeDataset(path, split="test")


def step_limit(episodes) -> int | None:
    """The step limit the episodes were recorded under (a data set's manifest says it), or None:
    an episode that reached it was cut there, not ended by the game (`ChunkStream`)."""
    if isinstance(episodes, store.EpisodeDataset):
        limit = episodes.manifest.get("config", {}).get("max_steps")
        return None if limit is None else int(limit)
    return None


def data_action_dim(episodes) -> int:
    """Values per action of an episode source: a data set's manifest says it; else the first
    episode's actions."""
    if isinstance(episodes, store.EpisodeDataset) and "action_dim" in episodes.manifest.get("data", {}):
        return int(episodes.manifest["data"]["action_dim"])
    if len(episodes) == 0:
        raise ValueError("the run's data holds no training episodes")
    return int(episodes[0].actions.shape[1])


def with_data_dims(cfg: RunConfig, train) -> RunConfig:
    """`cfg` with `action_dim` from its training data, so the action variants' encoder takes
    the data's actions (a gymnasium game's one-hot or rescaled actions, 3 for the built-in game)."""
    return dataclasses.replace(cfg, action_dim=data_action_dim(train))


def verify_data(cfg: RunConfig, train, test) -> None:
    """Check, before the first step and before anything is written, what a run's data must
    be: training and held-out episodes present (an empty held-out split would fail only the
    evaluation after training), every episode at least 2 frames long (one transition); for a
    data set directory (the built-in game's cached data included) every episode file of the
    splits: readable, CRCs intact, shapes, dtypes and lengths as the manifest says, frames
    of the preset's size. Raises `store.DatasetError` naming the first problem."""
    size = cfg.arch.image_size
    for name, split in (("training", train), ("held-out", test)):
        where = f"data set {split.path}" if isinstance(split, store.EpisodeDataset) else f"the run's {cfg.data} data"
        if len(split) == 0:
            how = (f" (its test split is empty: {split.manifest['config'].get('num_episodes')} episodes, test "
                   f"fraction {split.manifest['config'].get('test_fraction')}; record more episodes)"
                   if isinstance(split, store.EpisodeDataset) and name == "held-out" else "")
            raise store.DatasetError(f"{where} holds no {name} episodes{how}: a run needs both")
        lengths = split.lengths if isinstance(split, store.EpisodeDataset) else [len(e) for e in split]
        short = [i for i, n in enumerate(lengths) if n < 2]
        if short:
            which = (f"episode file {split.path / split.files[short[0]]}" if isinstance(split, store.EpisodeDataset)
                     else f"{name} episode {short[0]}")
            raise store.DatasetError(f"{which} of {where} has {lengths[short[0]]} frame(s); at least 2 are needed "
                                     f"for one transition ({len(short)} such episode(s) in the {name} split)")
        if not isinstance(split, store.EpisodeDataset):
            continue
        shape = split.manifest.get("data", {}).get("frame_shape")
        if shape is not None and tuple(shape) != (size, size):
            raise store.DatasetError(
                f"data set {split.path} holds {shape[0]}x{shape[1]} frames; preset {cfg.preset!r} takes "
                f"{size}x{size} (record the data at that size, or pick the preset that matches it)")
        collected = split.manifest.get("config", {})
        if collected.get("source") == "slither" and int(collected.get("max_filter", 1)) != cfg.arch.max_filter:
            raise store.DatasetError(
                f"data set {split.path} was shrunk after a max filter of side {collected.get('max_filter', 1)}; "
                f"this run sees the game after one of side {cfg.arch.max_filter} (--max-filter) "
                f"(collect it with --max-filter {cfg.arch.max_filter}, or train with the max filter it was "
                "collected with)")
        split.verify()


def frame_stats(episodes: Sequence[Episode], max_episodes: int = 16) -> tuple[float, float]:
    """Mean and standard deviation of the pixels of the first `max_episodes` episodes, as
    brightness in [0, 1]."""
    if len(episodes) == 0:
        raise ValueError("no episodes to measure frame statistics on")
    total = total_sq = count = 0.0
    for i in range(min(max_episodes, len(episodes))):
        frames = np.asarray(episodes[i].frames, np.float64)
        if episodes[i].frames.dtype == np.uint8:
            frames = frames / 255.0
        total += float(frames.sum())
        total_sq += float(np.square(frames).sum())
        count += frames.size
    mean = total / count
    std = float(np.sqrt(max(total_sq / count - mean * mean, 0.0)))
    if std == 0.0:
        raise ValueError("the frames are constant: obs_norm data cannot standardise them (use obs_norm none)")
    return mean, std


def stats_episodes(cfg: RunConfig, cache_root: Path) -> Sequence[Episode]:
    """The frames `obs_norm data` measures, the same for every seed (so a sweep over seeds
    is one architecture, and equals its single runs): a data set directory's training
    split; for the built-in game, 8 behaviour-switching episodes of its level and game
    parameters collected with seed 0 (online runs too); synthetic episodes of seed 0."""
    if cfg.data == "game":
        sample = dataclasses.replace(cfg, variant="main", episodes=8, seed=0, reward_balanced_weight=0.0,
                                     imagined_reward_balanced_weight=0.0, lookahead_steps=0, value_backup="lambda",
                                     frame_value_weight=0.0, advantage_weight=0.0, data_policy="auto")
    elif cfg.data == "synthetic":
        sample = dataclasses.replace(cfg, seed=0)
    else:
        sample = cfg
    return load_episodes(sample, cache_root)[0]


def with_obs_norm(cfg: RunConfig, cache_root: Path) -> RunConfig:
    """`cfg` with `obs_mean`/`obs_std` measured (`stats_episodes`) when `cfg.obs_norm` is 'data'
    (a run started from another, `init_from`, keeps the normalisation its model learnt on)."""
    if cfg.obs_norm != "data" or cfg.init_from:
        return cfg
    mean, std = frame_stats(stats_episodes(cfg, cache_root))
    return dataclasses.replace(cfg, obs_mean=mean, obs_std=std)


def run_game(cfg: RunConfig):
    """The game a controller run plays: the run's level and `cfg.env`, episodes capped at
    `cfg.episode_steps` unless `cfg.env` sets `max_steps`."""
    from envs.slither import level_game

    params = game_params(cfg)
    if "max_steps" not in cfg.env:
        params = params.replace(max_steps=np.asarray(cfg.episode_steps, np.int32))
    return level_game(cfg.level), params
