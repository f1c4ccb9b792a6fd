"""`RunConfig`: everything that defines a training run. The CLI's `train` and `sweep` options
map onto its fields (help texts and defaults come from here); `config.json` in a run
directory is its `dataclasses.asdict`."""
from __future__ import annotations

import dataclasses

from cdrl.models.arch import ArchConfig, preset


def _opt(default, help: str):
    return dataclasses.field(default=default, metadata={"help": help})


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Everything that defines a training run (the CLI's `train` options map onto it)."""

    variant: str = _opt("main", "model variant (see `cdrl variants`)")
    preset: str = _opt("small", "architecture preset: thesis (150x150, LSTM 512), small (64x64) or tiny")
    data: str = _opt("game", "'game' (collect from the built-in game and cache it), 'synthetic', or a data set directory")
    episodes: int = _opt(60, "episodes to collect when data is 'game' or 'synthetic'")
    episode_steps: int = _opt(200, "step limit of a collected episode")
    unroll: int = _opt(32, "truncated-BPTT length T")
    batch: int = _opt(1, "independent episode streams per step B")
    lr: float = _opt(0.1, "SGD learning rate")
    momentum: float = _opt(0.9, "SGD momentum")
    steps: int = _opt(1000, "training steps (chunks)")
    seed: int = _opt(0, "seed of the parameters and the data order")
    diverge_threshold: float = _opt(1e3, "a norm ratio ||grad||/||param|| above this stops the run")
    checkpoint_every: int = _opt(200, "steps between checkpoints")
    keep_checkpoints: int = _opt(3, "how many checkpoints to keep")
    eval_every: int = _opt(250, "steps between held-out evaluations (0: only at the end)")
    eval_episodes: int = _opt(4, "held-out episodes per evaluation (online variants: games per policy)")
    env: str = _opt("", "game parameters for the built-in game, e.g. 'max_steps=300,pellet_init_fill=0.3'")
    scope: str = _opt("controller", "online variants: parameters the reward ascent may change: controller or all")
    ascent: float = _opt(0.1, "online variants: lambda, the weight of the predicted-reward ascent term")
    reward_weight: float = _opt(0.1, "online variants: weight of the reward-prediction loss (SGD lr 0.1 with momentum 0.9 oscillates on it at 1)")
    noise_std: float = _opt(0.3, "online variants: std of the exploration noise on the controller's actions")
    noise_decay: float = _opt(0.999, "online variants: per-update decay factor of the exploration noise")
    warmup_steps: int = _opt(100, "online variants: updates of pure model learning before the ascent term")

    def __post_init__(self):
        preset(self.preset)
        for name in ("unroll", "batch", "steps", "episodes", "episode_steps", "checkpoint_every", "keep_checkpoints"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.scope not in ("controller", "all"):
            raise ValueError(f"scope must be 'controller' or 'all', got {self.scope!r}")
        if self.lr <= 0 or not 0 <= self.momentum < 1:
            raise ValueError(f"need lr > 0 and 0 <= momentum < 1, got lr={self.lr}, momentum={self.momentum}")

    @property
    def arch(self) -> ArchConfig:
        return preset(self.preset)


# Options that may change when a run is resumed (they do not change what the steps compute).
RESUMABLE = {"steps", "checkpoint_every", "keep_checkpoints", "eval_every", "eval_episodes"}
