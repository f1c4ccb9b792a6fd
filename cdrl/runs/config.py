"""`RunConfig`: everything that defines a training run. Its options are defined once, in the
sections of `cdrl.options` (game, model, optim, loss, control, schedule), with their defaults,
help texts and recipes; `RunConfig` holds the fields of all of them, flat (`cfg.lr`), and
`cfg.section("optim")` gives one section. The CLI's `train` and `sweep` options map onto its
fields. `config.json` in a run directory is `cfg.to_dict()`, nested by section.

A recipe fills every option of its table that the run does not set itself; the config written
to `config.json` holds the resolved values, so a run reads the same later whatever the recipes
become. Configs written flat by older versions, and under old names, still load
(`saved_config`, `upgrade`).
"""
from __future__ import annotations

import dataclasses
import math

from cdrl import learners
from cdrl.learners.onpolicy_ac import CRITIC_PLANS
from cdrl.learners.thesis_ascent import SCOPES
from cdrl.models import VARIANTS
from cdrl.models.arch import ArchConfig, preset
from cdrl.models.conv import FORMULATIONS
from cdrl.models.base import Variant
from cdrl.options import DEFAULT_RECIPE, RECIPES  # noqa: F401 (re-exported: the CLI's help and tests read them here)
from cdrl.options import (AGENT_RECIPE, FAMILY_OVERRIDES, OFFLINE_WORLD_MODEL, PRESET_ALIASES, RECIPE_ALIASES,
                          REPLAY_OVERRIDES, SECTIONS)
from cdrl.training.lookahead import VALUE_BACKUPS, LookaheadHParams
from cdrl.training.optim import OPTIMIZERS, SCHEDULES, HParams, OptHParams

OBS_NORMS = ("none", "data")


class _RunConfigMethods:
    """What `RunConfig` does with its fields: resolving the recipe and the old names, checking
    every value, and the model, optimiser and loss numbers they make."""

    def __post_init__(self, controller: str | None = None):
        named = {"variant": self.variant, "recipe": self.recipe, "preset": self.preset, "level": self.level}
        now = upgrade(named if controller is None else {**named, "controller": controller})
        if self.preset in PRESET_ALIASES and self.max_filter not in (1, now["max_filter"]):
            raise ValueError(f"preset {self.preset!r} is preset {now['preset']} with max_filter {now['max_filter']}; "
                             f"got max_filter {self.max_filter}")
        for name, value in now.items():
            object.__setattr__(self, name, value)
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
        from envs.policies import POLICIES
        from envs.slither import LEVELS

        curriculum = self.feed_curriculum  # refuses a malformed --multistep
        if self.kind != "offline" and curriculum != (1,):
            raise ValueError(f"multistep {self.multistep!r} is for offline runs (teacher-forced on recorded "
                             f"episodes); a {self.kind} run of {self.variant!r} plays its own frames")
        if self.lookahead_steps > 0:
            self.check_lookahead()
        elif self.imagined_reward_balanced_weight > 0:
            raise ValueError(f"imagined_reward_balanced_weight {self.imagined_reward_balanced_weight!r} weighs the "
                             "imagined steps' reward error; turn the imagination on with lookahead_steps >= 1")
        elif self.value_backup != "lambda" or self.frame_value_weight > 0 or self.advantage_weight > 0:
            raise ValueError(f"value_backup {self.value_backup!r}, frame_value_weight {self.frame_value_weight!r} and "
                             f"advantage_weight {self.advantage_weight!r} set the look-ahead's value heads; turn the "
                             "heads on with lookahead_steps >= 1")
        if self.mirror_streams and (self.kind != "offline" or self.data != "game" or self.batch < 2):
            raise ValueError(f"mirror_streams mirrors half of an offline run's streams of the built-in game (a {self.kind} "
                             f"run on data {self.data!r} with batch {self.batch}): it needs learner world_model or a "
                             "variant without a controller, data 'game' and batch >= 2")
        takes_balanced = (self.kind != "model_free" and VARIANTS[self.variant].predicts_reward
                          and not (self.kind == "online" and self.learner == "thesis_ascent"))
        if (self.reward_balanced_weight > 0 or self.imagined_reward_balanced_weight > 0) and not takes_balanced:
            raise ValueError(f"reward_balanced_weight {self.reward_balanced_weight!r} weighs a reward head's error in "
                             f"offline training and the replay learners' model updates; {self.variant!r} "
                             f"{'with learner thesis_ascent ' if self.kind == 'online' else ''}has no such term "
                             "(reward_prediction or final_proposal, offline or with a learner that keeps a replay "
                             "buffer)")
        choices = {"scope": SCOPES, "optimizer": tuple(OPTIMIZERS), "lr_schedule": SCHEDULES,
                   "obs_norm": OBS_NORMS, "level": tuple(LEVELS), "conv": FORMULATIONS,
                   "data_policy": ("auto",) + tuple(POLICIES), "value_backup": VALUE_BACKUPS,
                   "critic_plan": CRITIC_PLANS}
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {', '.join(allowed)}; got {getattr(self, name)!r}")
        if self.critic_plan != "off" and (self.kind != "online" or self.learner != "onpolicy_ac"):
            raise ValueError(f"critic_plan {self.critic_plan!r} plans with onpolicy_ac's critic; got learner "
                             f"{self.learner!r}")
        if self.kind == "offline" and self.data != "game":
            for name, default in (("env", ""), ("level", "thesis")):
                if getattr(self, name) != default:
                    raise ValueError(f"{name} {getattr(self, name)!r} sets the built-in game, which a run on data "
                                     f"{self.data!r} never plays (it trains on recorded episodes); drop it, or "
                                     "train on data 'game'")

    def check_lookahead(self):
        """The look-ahead losses imagine through the model's own actions, on chunks it learns from
        teacher-forced: a controller variant, offline or with a replay learner."""
        learner = self.learner
        replay = learner != learners.OFFLINE and self.kind == "online" and \
            learners.learner_class(learner).recipe_family == "replay"
        if not VARIANTS[self.variant].has_controller or not (self.kind == "offline" or replay):
            raise ValueError(f"lookahead_steps {self.lookahead_steps} trains a controller variant (action_loop, "
                             "reward_prediction, final_proposal) offline or with a learner that keeps a replay buffer; "
                             f"got variant {self.variant!r} with learner {learner!r}")
        if self.feed_curriculum != (1,):
            raise ValueError(f"lookahead_steps and multistep {self.multistep!r} both train on the model's own "
                             "predictions; choose one")
        if self.advantage_weight > 0 and learner == "mpc_planner" and self.horizon != 1:
            raise ValueError(f"advantage_weight {self.advantage_weight!r} ranks one-step plans; mpc_planner's "
                             f"horizon must be 1, got {self.horizon}")

    def lookahead_hparams(self):
        """The look-ahead's numbers (`cdrl.training.lookahead.LookaheadHParams`), None when off."""
        if self.lookahead_steps == 0:
            return None
        return LookaheadHParams.create(steps=self.lookahead_steps, stride=self.lookahead_stride or None,
                                       head_opt=OptHParams.create("adam", lr=self.ctrl_lr, grad_clip=100.0),
                                       gamma=self.gamma, lam=self.gae_lambda, target_decay=self.value_target_decay,
                                       head_grad=self.head_grad, backup=self.value_backup,
                                       frame_value=self.frame_value_weight > 0, advantage=self.advantage_weight > 0)

    def recipe_values(self) -> dict[str, object]:
        """The options the run's recipe sets for its variant and learner."""
        if self.kind == "model_free":
            return AGENT_RECIPE
        if not VARIANTS[self.variant].has_controller:
            return RECIPES[self.recipe]
        if self.learner == learners.OFFLINE:  # offline, teacher-forced as the replay learner's model is
            return {**RECIPES[self.recipe], **REPLAY_OVERRIDES[self.recipe], **OFFLINE_WORLD_MODEL[self.recipe]}
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
                                   fc_init_gain=self.fc_init_gain, action_dim=self.action_dim,
                                   max_filter=self.max_filter, conv=self.conv)

    def section(self, name: str):
        """The options of section `name` (`cdrl.options.SECTIONS`) as that section's dataclass."""
        cls = SECTIONS[name]
        return cls(**{f.name: getattr(self, f.name) for f in dataclasses.fields(cls)})

    def to_dict(self) -> dict[str, dict]:
        """The config nested by section, as `config.json` holds it."""
        return {name: dataclasses.asdict(self.section(name)) for name in SECTIONS}

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
        weights = {"reward_mse": self.reward_weight, "reward_balanced": self.reward_balanced_weight} \
            if variant.predicts_reward else {}
        heads = self.lookahead_hparams()
        if heads is not None:
            weights.update(imag_obs_bce=self.imagined_frame_weight, imag_reward_mse=self.reward_weight,
                           imag_reward_balanced=self.imagined_reward_balanced_weight,
                           reward_twohot=self.reward_head_weight, cont_bce=self.cont_weight,
                           value_twohot=self.value_weight, frame_value_twohot=self.frame_value_weight,
                           advantage_mse=self.advantage_weight)
        return HParams.create(variant, opt=self.opt_hparams(), diverge_threshold=self.diverge_threshold,
                              loss_weights=weights or None, feed_every=ks[0],
                              fed=max(ks) > 1 if fed is None else fed, lookahead=heads, mirror=self.mirror_streams)


def _fields() -> list[tuple]:
    """Every section's fields, as `dataclasses.make_dataclass` takes them, then the old name of
    `learner` (`controller`, init-only, kept for one release)."""
    out = [(f.name, f.type, dataclasses.field(default=f.default, metadata=f.metadata))
           for cls in SECTIONS.values() for f in dataclasses.fields(cls)]
    return out + [("controller", dataclasses.InitVar[str | None], dataclasses.field(default=None))]


RunConfig = dataclasses.make_dataclass("RunConfig", _fields(), bases=(_RunConfigMethods,), frozen=True,
                                       namespace={"__doc__": "Everything that defines a training run: the options "
                                                             "of every section of `cdrl.options`, flat."})
RunConfig.__module__ = __name__


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
                     "horizon", "max_filter"), AT_LEAST_1),
    **dict.fromkeys(("lookahead_steps", "lookahead_stride", "imagined_frame_weight", "imagined_reward_balanced_weight",
                     "reward_head_weight", "cont_weight", "value_weight", "frame_value_weight", "advantage_weight",
                     "head_grad", "plan_weight"),
                    AT_LEAST_0),
    "value_target_decay": FRACTION,
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


def upgrade(saved: dict) -> dict:
    """A config as `config.json` or a checkpoint holds it, nested by section or flat (older
    versions), as flat options under today's names: `controller` is `learner`, variant ppo is
    learner ppo, recipe fast is tuned, preset small-max is small with max_filter 5, a level's old
    name is its new one (`envs.slither.LEVEL_ALIASES`)."""
    from envs.slither import LEVEL_ALIASES  # not with this module: see `RunConfig.__post_init__`

    flat = dict(saved)
    for name in SECTIONS:
        if isinstance(flat.get(name), dict):
            flat.update(flat.pop(name))
    if "controller" in flat:
        flat.setdefault("learner", flat.pop("controller"))
    if flat.get("variant") == "ppo":
        flat.update(variant="main", learner="ppo")
    if flat.get("recipe") in RECIPE_ALIASES:
        flat["recipe"] = RECIPE_ALIASES[flat["recipe"]]
    if flat.get("preset") in PRESET_ALIASES:
        flat["preset"], flat["max_filter"] = PRESET_ALIASES[flat["preset"]]
    if flat.get("level") in LEVEL_ALIASES:
        flat["level"] = LEVEL_ALIASES[flat["level"]]
    return flat


def saved_config(saved: dict) -> RunConfig:
    """A `RunConfig` from a `config.json`: nested by section, or flat as older versions wrote
    it, its options under old names or new (`upgrade`). A config written before
    recipes existed holds no recipe: the options it lacks are the thesis recipe's, which is how
    it was trained."""
    return RunConfig(**{"recipe": "thesis", **upgrade(saved)})


# Options that may change when a run is resumed (they do not change what the steps compute).
# `devices` lays the same computation out over devices (equal up to the order of float sums).
RESUMABLE = {"steps", "checkpoint_every", "keep_checkpoints", "eval_every", "eval_episodes", "tensorboard", "devices"}
