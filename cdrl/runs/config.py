"""`RunConfig`: everything that defines a training run. The CLI's `train` and `sweep` options
map onto its fields (help texts and defaults come from here); `config.json` in a run
directory is its `dataclasses.asdict`.

How a model is trained comes in named recipes (`RECIPES`): `thesis` is the thesis's
training exactly (SGD lr 0.1, momentum 0.9, batch 1, raw [0, 1] brightness into the
encoder, the initialisation of its section 4.3.1); `fast` is the quickest route to a model
that beats copying the last frame that cdrl has measured (see the README's "Learning"
section). A recipe fills every option of its table that the run does not set itself; the
config written to `config.json` holds the resolved values, so a run reads the same later
whatever the recipes become.
"""
from __future__ import annotations

import dataclasses
import math

from cdrl.models import VARIANTS
from cdrl.models.arch import ArchConfig, preset
from cdrl.models.base import Variant
from cdrl import learners
from cdrl.learners.thesis_ascent import SCOPES
from cdrl.training.optim import OPTIMIZERS, SCHEDULES, HParams, OptHParams

# option -> value, per recipe. Options not listed keep their field default.
RECIPES: dict[str, dict[str, object]] = {
    "thesis": {
        "optimizer": "sgd", "lr": 0.1, "momentum": 0.9, "b2": 0.999, "weight_decay": 0.0, "grad_clip": 0.0,
        "lr_schedule": "constant", "lr_warmup": 0, "batch": 1, "unroll": 32, "obs_norm": "none",
        "fc_init_gain": 1.0, "reward_weight": 0.1,
    },
    "fast": {
        "optimizer": "sgd", "lr": 2.0, "momentum": 0.9, "b2": 0.999, "weight_decay": 0.0, "grad_clip": 0.0,
        "lr_schedule": "constant", "lr_warmup": 0, "batch": 4, "unroll": 8, "obs_norm": "data",
        "fc_init_gain": 5.0, "reward_weight": 0.1,
    },
}
# Controller variants train online against the game on their own actions; their reward
# terms make large steps diverge (measured: lr 1, or an FC gain of 5, blow up within 10
# updates), so `fast` keeps the controller experiments' rate, streams and horizon for them.
ONLINE_OVERRIDES: dict[str, dict[str, object]] = {
    "thesis": {},
    "fast": {"lr": 0.1, "batch": 8, "unroll": 16, "fc_init_gain": 1.0},
}
# With a replay buffer (controllers imagine and critic) the model learns teacher-forced, as
# offline, so `fast` takes the offline rate of the closed loops (lr 1; lr 2 diverges online as
# offline) and its FC gain; the reward term's weight is 0.01 (at lr 1 and weight 0.1 the reward
# head's squared error grows without bound within 5 updates).
DREAM_OVERRIDES: dict[str, dict[str, object]] = {
    "thesis": {},
    "fast": {"lr": 1.0, "fc_init_gain": 5.0, "reward_weight": 0.01},
}
# A controller variant's world model trained offline (`--controller none`) learns its frames
# alone: with one SGD optimiser for everything its reward term's gradient kills the core
# (measured, final_proposal, small preset, lr 1: at weight 0.01 the reward error jumps from
# 0.15 to 7 at step 1 and every LSTM and encoder gradient is 0 by step 50, the held-out excess
# ratio stuck at 1.46; at weight 0 it reaches 0.74 in 4000 steps). Its reward head is left to
# the online run, which steps it with its own optimiser (`cdrl.learners.replay_base`).
OFFLINE_WORLD_MODEL: dict[str, dict[str, object]] = {"thesis": {}, "fast": {"reward_weight": 0.0}}
# Policies trained without a world model, and what every recipe sets for them: PPO's usual
# numbers (Adam lr 2.5e-4, gradient norm clipped at 0.5, 16 games x 32 steps per update).
AGENT_RECIPE: dict[str, object] = {
    "optimizer": "adam", "lr": 2.5e-4, "momentum": 0.9, "b2": 0.999, "weight_decay": 0.0, "grad_clip": 0.5,
    "lr_schedule": "constant", "lr_warmup": 0, "batch": 16, "unroll": 32, "obs_norm": "data", "fc_init_gain": 1.0,
    "reward_weight": 0.0,
}
# What each family of learners (`Learner.recipe_family`) takes over its recipe's numbers.
FAMILY_OVERRIDES: dict[str, dict[str, dict[str, object]]] = {
    "ascent": ONLINE_OVERRIDES,
    "replay": {name: {**ONLINE_OVERRIDES[name], **DREAM_OVERRIDES[name]} for name in RECIPES},
}
DEFAULT_RECIPE = "fast"
OBS_NORMS = ("none", "data")


def _opt(default, help: str):
    return dataclasses.field(default=default, metadata={"help": help})


def _recipe_opt(help: str):
    """An option whose default comes from the run's recipe."""
    return dataclasses.field(default=None, metadata={"help": help, "recipe": True})


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Everything that defines a training run (the CLI's `train` options map onto it)."""

    variant: str = _opt("main", "model variant (see `cdrl variants`); the world model of a model-based learner")
    preset: str = _opt("small", "architecture preset: thesis (150x150, LSTM 512), small (64x64), small-128 (its "
                                "networks on 128x128), small-max (small, the frame shrunk after a 5x5 max filter) "
                                "or tiny")
    recipe: str = _opt(DEFAULT_RECIPE, f"training recipe filling the options it names: {' or '.join(RECIPES)}")
    data: str = _opt("game", "'game' (collect from the built-in game and cache it), 'synthetic', or a data set directory")
    level: str = _opt("thesis", "level of the built-in game (data collection and online play): thesis, flat, sparse, "
                                "clean, visible, heading, thesis-heading, thesis-flow (envs.slither.LEVELS)")
    episodes: int = _opt(60, "episodes to collect when data is 'game' or 'synthetic'")
    episode_steps: int = _opt(200, "step limit of a collected episode")
    unroll: int = _recipe_opt("truncated-BPTT length T")
    batch: int = _recipe_opt("independent episode streams per step B")
    optimizer: str = _recipe_opt(f"optimiser: {', '.join(OPTIMIZERS)}")
    lr: float = _recipe_opt("learning rate (the peak of the schedule)")
    momentum: float = _recipe_opt("SGD momentum; beta1 of adam, adamw, lion; momentum of rmsprop")
    b2: float = _recipe_opt("beta2 of adam, adamw, lion; squared-gradient decay of rmsprop")
    weight_decay: float = _recipe_opt("decoupled weight decay (adamw, lion)")
    grad_clip: float = _recipe_opt("largest global gradient norm (0: no clipping)")
    lr_schedule: str = _recipe_opt(f"learning-rate schedule: {' or '.join(SCHEDULES)} (cosine: from lr to 0 over lr_decay_steps)")
    lr_warmup: int = _recipe_opt("steps of linear learning-rate warm-up from 0 (0: none)")
    lr_decay_steps: int = _opt(0, "length of the cosine decay (0: the run's steps, fixed when the run starts)")
    obs_norm: str = _recipe_opt("encoder input: none (raw [0, 1] brightness, the thesis) or data (standardised "
                                "by the training frames' mean and std, measured when the run starts)")
    obs_mean: float = _opt(0.0, "brightness subtracted from the encoder's input (set by obs_norm data)")
    obs_std: float = _opt(1.0, "divisor of the encoder's input (set by obs_norm data)")
    action_dim: int = _opt(3, "values per action, the action encoder's input (set from the data when the run starts)")
    fc_init_gain: float = _recipe_opt("scale of the core's FC layer's LeCun-normal initial kernel (1: the thesis)")
    steps: int = _opt(1000, "training steps (chunks)")
    seed: int = _opt(0, "seed of the parameters and the data order")
    diverge_threshold: float = _opt(1e3, "a norm ratio ||grad||/||param|| above this stops the run")
    devices: int = _opt(1, "devices to spread over (0: every device of every process): a run's B streams "
                           "(data parallel; B a multiple of it), or a sweep's configurations")
    checkpoint_every: int = _opt(200, "steps between checkpoints")
    keep_checkpoints: int = _opt(3, "how many checkpoints to keep")
    eval_every: int = _opt(250, "steps between held-out evaluations (0: only at the end)")
    eval_episodes: int = _opt(4, "held-out episodes per evaluation (online variants: games per policy)")
    tensorboard: bool = _opt(True, "also write TensorBoard event files to RUN_DIR/tb (view: tensorboard --logdir runs)")
    env: str = _opt("", "game parameters over the level's, e.g. 'max_steps=300,pellet_init_fill=0.3'")
    scope: str = _opt("controller", "online variants, rollout and real: parameters the reward ascent (rollout) or the "
                                    "actor-critic (real) may change: controller or all")
    ascent: float = _opt(0.1, "online variants: lambda, the weight of the predicted-reward ascent term")
    reward_weight: float = _recipe_opt("online variants: weight of the reward-prediction loss (SGD lr 0.1 with momentum "
                                       "0.9 oscillates on it at 1)")
    reward_balanced_weight: float = _opt(0.0, "reward variants (offline and the replay learners' model): weight of the "
                                              "reward's squared error balanced over its sign classes (-, 0, +: each "
                                              "class present weighs alike), which teaches the core rare rewards")
    noise_std: float = _opt(0.3, "online variants: exploration: the std of the noise on the controller's actions "
                                 "(rollout), the chance a button is drawn uniformly (imagine, critic, value)")
    noise_decay: float = _opt(0.999, "online variants: per-update decay factor of the exploration")
    warmup_steps: int = _opt(100, "online variants: updates of pure model learning before the ascent term")
    learner: str = _opt("thesis_ascent", "how a controller variant learns to control (`cdrl learners`): "
                                         "thesis_ascent (the thesis: reward ascent through the real chunk), "
                                         "imagined_ascent (ascent through imagined rollouts), imagination_ac (an "
                                         "actor-critic in imagination), one_step_q (the buttons' values one model "
                                         "step ahead, from real returns), onpolicy_ac (an actor-critic on the "
                                         "model's states of the chunk just played, from its real rewards); the "
                                         "last four keep a replay buffer. world_model: no controller, the world "
                                         "model learns offline on recorded episodes, a start for --init-from. ppo: "
                                         "model-free, from the same frames, whatever the variant. Old names: "
                                         "rollout, imagine, critic, value, real, none")
    init_from: str = _opt("", "a run directory whose trained world model (its newest good checkpoint; same variant "
                              "and preset) this run starts from, with its input normalisation ('': a fresh model)")
    replay: int = _opt(64, "online variants, imagine, critic, value and real: chunks kept in the replay buffer")
    model_updates: int = _opt(4, "online variants, imagine, critic, value and real: model updates per collected chunk")
    horizon: int = _opt(15, "online variants, imagine and critic: imagined steps")
    ctrl_lr: float = _opt(3e-4, "online variants, imagine, critic, value and real: Adam learning rate of the controller and critic")
    gamma: float = _opt(0.99, "ppo, critic, value and imagine: discount of future reward")
    gae_lambda: float = _opt(0.95, "ppo: lambda of generalised advantage estimation; critic, value and real: of the lambda-returns")
    clip_eps: float = _opt(0.2, "ppo and real: clip range of the probability ratio (and of the value)")
    value_coef: float = _opt(0.5, "ppo: weight of the value loss")
    entropy_coef: float = _opt(0.01, "ppo, critic, value and real: weight of the entropy bonus")
    ppo_epochs: int = _opt(4, "ppo and real: passes over each rollout")
    ppo_minibatches: int = _opt(4, "ppo: minibatches per pass (batch x unroll must divide by it)")
    multistep: str = _opt("1", "offline runs: multi-step training: K feeds the model its own prediction between "
                               "real frames every K steps of a chunk (1: teacher forcing); 'K1,K2,...' a "
                               "curriculum over equal parts of --steps (Oh et al. 2015: 1,3,5)")

    controller: dataclasses.InitVar[str | None] = None  # the old name of `learner`, kept for one release

    def __post_init__(self, controller: str | None = None):
        if controller is not None:
            object.__setattr__(self, "learner", controller)
        if self.variant == "ppo":  # the old way to name the model-free learner
            object.__setattr__(self, "learner", "ppo")
            object.__setattr__(self, "variant", "main")
        object.__setattr__(self, "learner", learners.canonical(self.learner))
        if self.recipe not in RECIPES:
            raise ValueError(f"unknown recipe {self.recipe!r}; choose one of {sorted(RECIPES)}")
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown variant {self.variant!r}; choose one of {sorted(VARIANTS)}")
        for name, value in self.recipe_values().items():
            if getattr(self, name) is None:
                object.__setattr__(self, name, value)
        if self.lr_schedule == "cosine" and self.lr_decay_steps == 0:
            object.__setattr__(self, "lr_decay_steps", self.steps)
        preset(self.preset)
        for f in dataclasses.fields(self):
            check_value(f.name, f.type, getattr(self, f.name))
        # The game's package is imported here, not with this module: `cdrl train --distributed`
        # must start jax.distributed before anything touches a JAX backend.
        from envs.slither import LEVELS

        curriculum = self.feed_curriculum  # refuses a malformed --multistep
        if self.kind != "offline" and curriculum != (1,):
            raise ValueError(f"multistep {self.multistep!r} is for offline runs (teacher-forced on recorded "
                             f"episodes); a {self.kind} run of {self.variant!r} plays its own frames")
        takes_balanced = (self.kind != "model_free" and VARIANTS[self.variant].predicts_reward
                          and not (self.kind == "online" and self.learner == "thesis_ascent"))
        if self.reward_balanced_weight > 0 and not takes_balanced:
            raise ValueError(f"reward_balanced_weight {self.reward_balanced_weight!r} weighs a reward head's error in "
                             f"offline training and the replay learners' model updates; {self.variant!r} "
                             f"{'with learner thesis_ascent ' if self.kind == 'online' else ''}has no such term "
                             "(reward_prediction or final_proposal, offline or with a learner that keeps a replay "
                             "buffer)")
        choices = {"scope": SCOPES, "optimizer": tuple(OPTIMIZERS), "lr_schedule": SCHEDULES,
                   "obs_norm": OBS_NORMS, "level": tuple(LEVELS)}
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {', '.join(allowed)}; got {getattr(self, name)!r}")
        if self.kind == "offline" and self.data != "game":
            for name, default in (("env", ""), ("level", "thesis")):
                if getattr(self, name) != default:
                    raise ValueError(f"{name} {getattr(self, name)!r} sets the built-in game, which a run on data "
                                     f"{self.data!r} never plays (it trains on recorded episodes); drop it, or "
                                     "train on data 'game'")

    def recipe_values(self) -> dict[str, object]:
        """The options the run's recipe sets for its variant and learner."""
        if self.kind == "model_free":
            return AGENT_RECIPE
        if not VARIANTS[self.variant].has_controller:
            return RECIPES[self.recipe]
        if self.learner == learners.OFFLINE:  # offline, teacher-forced as the replay learner's model is
            return {**RECIPES[self.recipe], **DREAM_OVERRIDES[self.recipe], **OFFLINE_WORLD_MODEL[self.recipe]}
        family = learners.learner_class(self.learner).recipe_family
        return {**RECIPES[self.recipe], **FAMILY_OVERRIDES[family][self.recipe]}

    @property
    def kind(self) -> str:
        """How the run trains: "offline" on recorded episodes (a controller variant too, with
        learner world_model), "online" (a learner that plays the game with a world model) or
        "model_free" (one that plays without: PPO, or another model-free learner)."""
        if self.learner != learners.OFFLINE and not learners.learner_class(self.learner).has_world_model:
            return "model_free"
        return "online" if VARIANTS[self.variant].has_controller and self.learner != learners.OFFLINE else "offline"

    @property
    def arch(self) -> ArchConfig:
        return dataclasses.replace(preset(self.preset), obs_mean=self.obs_mean, obs_std=self.obs_std,
                                   fc_init_gain=self.fc_init_gain, action_dim=self.action_dim)

    def opt_hparams(self) -> OptHParams:
        """The optimiser's traced numbers."""
        return OptHParams.create(name=self.optimizer, lr=self.lr, momentum=self.momentum, b2=self.b2,
                                 weight_decay=self.weight_decay, grad_clip=self.grad_clip, warmup=self.lr_warmup,
                                 decay_steps=self.lr_decay_steps if self.lr_schedule == "cosine" else 0)

    @property
    def feed_curriculum(self) -> tuple[int, ...]:
        """`multistep` as its K of each equal part of the run's steps."""
        try:
            ks = tuple(int(k) for k in self.multistep.split(","))
        except ValueError:
            ks = ()
        if not ks or min(ks) < 1:
            raise ValueError(f"multistep must be K or K1,K2,... with every K an integer >= 1 (1: teacher forcing), "
                             f"got {self.multistep!r}")
        return ks

    def hparams(self, variant: Variant, fed: bool | None = None) -> HParams:
        """The traced hyper-parameters of offline training (a reward head's terms weighted by
        `reward_weight` and `reward_balanced_weight`; the curriculum's first K; `fed`: unroll
        with fed-back predictions, by default where the curriculum has a K above 1)."""
        ks = self.feed_curriculum
        return HParams.create(variant, opt=self.opt_hparams(), diverge_threshold=self.diverge_threshold,
                              loss_weights={"reward_mse": self.reward_weight,
                                            "reward_balanced": self.reward_balanced_weight}
                              if variant.predicts_reward else None,
                              feed_every=ks[0], fed=max(ks) > 1 if fed is None else fed)


@dataclasses.dataclass(frozen=True)
class Range:
    """The values a numeric option may take: finite numbers from `low` to `high` (None: no
    bound), each end included unless it is open."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False

    def __contains__(self, value) -> bool:
        return ((self.low is None or (value > self.low if self.low_open else value >= self.low))
                and (self.high is None or (value < self.high if self.high_open else value <= self.high)))

    def describe(self, name: str) -> str:
        """The range as a condition on option `name`: 'steps >= 1', '0 <= b2 < 1'."""
        if self.high is None:
            return f"{name} {'>' if self.low_open else '>='} {self.low:g}"
        return f"{self.low:g} {'<' if self.low_open else '<='} {name} {'<' if self.high_open else '<='} {self.high:g}"


AT_LEAST_1, AT_LEAST_0, ABOVE_0 = Range(1), Range(0), Range(0, low_open=True)
FRACTION, BELOW_1 = Range(0, 1), Range(0, 1, high_open=True)
# The range of every numeric option (a float field not listed takes any finite value). Every
# number must be finite: config.json holds JSON, which has no NaN or infinity.
RANGES: dict[str, Range] = {
    **dict.fromkeys(("unroll", "batch", "steps", "episodes", "episode_steps", "checkpoint_every", "keep_checkpoints",
                     "action_dim", "eval_episodes", "ppo_epochs", "ppo_minibatches", "replay", "model_updates",
                     "horizon"), AT_LEAST_1),
    **dict.fromkeys(("lr_warmup", "lr_decay_steps", "seed", "devices", "eval_every", "warmup_steps", "weight_decay",
                     "grad_clip", "ascent", "reward_weight", "reward_balanced_weight", "noise_std", "value_coef",
                     "entropy_coef"), AT_LEAST_0),
    **dict.fromkeys(("lr", "obs_std", "fc_init_gain", "diverge_threshold", "ctrl_lr", "clip_eps"), ABOVE_0),
    **dict.fromkeys(("momentum", "b2"), BELOW_1),
    **dict.fromkeys(("gamma", "gae_lambda"), FRACTION),
    "noise_decay": Range(0, 1, low_open=True),
}
_KINDS = {"int": (int,), "float": (int, float), "bool": (bool,), "str": (str,)}


def check_value(name: str, kind: str, value) -> None:
    """Refuse (ValueError naming the option) a value of option `name` (of type `kind`: a
    RunConfig field's annotation) of the wrong type, not finite, or outside `RANGES`."""
    if not isinstance(value, _KINDS[kind]) or (kind != "bool" and isinstance(value, bool)):
        raise ValueError(f"{name} must be {'an' if kind == 'int' else 'a'} {kind}, got {value!r}")
    if kind not in ("int", "float"):
        return
    if not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r} (a run's config.json holds JSON numbers)")
    if name in RANGES and value not in RANGES[name]:
        condition = RANGES[name].describe(name)
        raise ValueError(f"{condition.replace(name, name + ' must be', 1) if condition.startswith(name) else 'need ' + condition}"
                         f", got {value!r}")


def saved_config(saved: dict) -> RunConfig:
    """A `RunConfig` from a `config.json`. A config written before recipes existed holds
    no recipe: the options it lacks are the thesis recipe's, which is how it was trained. Its
    learner may go by an old name (`controller`, `variant` ppo)."""
    return RunConfig(**{"recipe": "thesis", **saved})


# Options that may change when a run is resumed (they do not change what the steps compute).
# `devices` lays the same computation out over devices (equal up to the order of float sums).
RESUMABLE = {"steps", "checkpoint_every", "keep_checkpoints", "eval_every", "eval_episodes", "tensorboard", "devices"}
