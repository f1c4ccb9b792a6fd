"""Every option of a run, once, with its default: the one source of defaults.

Options come in sections, each a frozen dataclass: the game, the model, the optimiser, the world
model's loss, the learner (`control`) and the run's schedule. `cdrl.runs.config.RunConfig`
holds the fields of all six; a run's `config.json` is nested by section.

A field's metadata holds its help text (the `cdrl train` option's), whether a recipe sets its
default (`recipe`), and whether it is a traced number (`traced`): one compiled program serves
every value of a traced option, so a `vmap` sweep can vary it.

Recipes are named overrides of the defaults, in the style of dreamerv3's `configs.yaml`:
`thesis` is the thesis's training exactly (SGD lr 0.1, momentum 0.9, batch 1, raw [0, 1]
brightness into the encoder, the initialisation of its section 4.3.1); `tuned` is the quickest
route to a model that beats copying the last frame that cdrl has measured (docs/training.md).
A learner's family (`cdrl.learners.api.Learner.recipe_family`) adds its own overrides.
"""
from __future__ import annotations

import dataclasses

# Old names, kept for one release: runs written before the renaming still load.
RECIPE_ALIASES = {"fast": "tuned"}
PRESET_ALIASES = {"small-max": ("small", 5)}  # name -> (preset, max_filter)


def _opt(default, help: str, traced: bool = False):
    return dataclasses.field(default=default, metadata={"help": help, "traced": traced})


def _recipe_opt(help: str, traced: bool = False):
    """An option whose default comes from the run's recipe."""
    return dataclasses.field(default=None, metadata={"help": help, "recipe": True, "traced": traced})


@dataclasses.dataclass(frozen=True)
class GameOptions:
    """The built-in game, and the data an offline run learns from."""

    data: str = _opt("game", "'game' (collect from the built-in game and cache it), 'synthetic', or a data set directory")
    level: str = _opt("thesis", "level of the built-in game (data collection and online play): thesis, flat, sparse, "
                                "clean, visible, turned-true-visible, turned-true, turned-redrawn, turned "
                                "(envs.slither.LEVELS); heading, thesis-heading and thesis-flow are the old names of "
                                "turned-true-visible, turned-true and turned-redrawn")
    env: str = _opt("", "game parameters over the level's, e.g. 'max_steps=300,pellet_init_fill=0.3'")
    episodes: int = _opt(60, "episodes to collect when data is 'game' or 'synthetic'")
    episode_steps: int = _opt(200, "step limit of a collected episode")
    data_policy: str = _opt("auto", "data 'game': the policy that plays the collected episodes, one of "
                                    "envs.policies.POLICIES (behaviour, uniform, held_uniform, never_accelerate, "
                                    "seldom_accelerate); "
                                    "auto: uniform for a variant that takes actions, else behaviour (the thesis's)")


@dataclasses.dataclass(frozen=True)
class ModelOptions:
    """The world model: its variant, architecture and input."""

    variant: str = _opt("main", "model variant (see `cdrl variants`); the world model of a model-based learner")
    preset: str = _opt("small", "architecture preset: thesis (150x150, LSTM 512), small (64x64), small-128 (its "
                                "networks on 128x128) or tiny; small-max is the old name of small with max_filter 5")
    max_filter: int = _opt(1, "side of a max filter applied to the game's frames before they are shrunk to the "
                              "preset's size (1: none; 5 keeps a pellet visible at 64x64)")
    obs_norm: str = _recipe_opt("encoder input: none (raw [0, 1] brightness, the thesis) or data (standardised "
                                "by the training frames' mean and std, measured when the run starts)")
    obs_mean: float = _opt(0.0, "brightness subtracted from the encoder's input (set by obs_norm data)")
    obs_std: float = _opt(1.0, "divisor of the encoder's input (set by obs_norm data)")
    action_dim: int = _opt(3, "values per action, the action encoder's input (set from the data when the run starts)")
    fc_init_gain: float = _recipe_opt("scale of the core's FC layer's LeCun-normal initial kernel (1: the thesis)")
    conv: str = _opt("auto", "convolution backend: auto (the environment's CDRL_CONV_FORMULATION, else XLA's CPU "
                             "formulation on the CPU and native elsewhere), cpu, native, or onednn (oneDNN's "
                             "convolutions as XLA custom calls, where the extension is built; else cpu, warned)")


@dataclasses.dataclass(frozen=True)
class OptimOptions:
    """The world model's optimiser (a model-free learner's too) and the divergence check."""

    optimizer: str = _recipe_opt("optimiser: sgd, momentum, adam, adamw, rmsprop, lion")
    lr: float = _recipe_opt("learning rate (the peak of the schedule)", traced=True)
    momentum: float = _recipe_opt("SGD momentum; beta1 of adam, adamw, lion; momentum of rmsprop", traced=True)
    b2: float = _recipe_opt("beta2 of adam, adamw, lion; squared-gradient decay of rmsprop", traced=True)
    weight_decay: float = _recipe_opt("decoupled weight decay (adamw, lion)", traced=True)
    grad_clip: float = _recipe_opt("largest global gradient norm (0: no clipping)", traced=True)
    lr_schedule: str = _recipe_opt("learning-rate schedule: constant or cosine (cosine: from lr to 0 over "
                                   "lr_decay_steps)")
    lr_warmup: int = _recipe_opt("steps of linear learning-rate warm-up from 0 (0: none)", traced=True)
    lr_decay_steps: int = _opt(0, "length of the cosine decay (0: the run's steps, fixed when the run starts)",
                               traced=True)
    diverge_threshold: float = _opt(1e3, "a norm ratio ||grad||/||param|| above this stops the run", traced=True)


@dataclasses.dataclass(frozen=True)
class LossOptions:
    """The world model's loss beside the frames' BCE."""

    reward_weight: float = _recipe_opt("reward variants: weight of the reward-prediction loss (SGD lr 0.1 with "
                                       "momentum 0.9 oscillates on it at 1)", traced=True)
    reward_balanced_weight: float = _opt(0.0, "reward variants (offline and the replay learners' model): weight of the "
                                              "reward's squared error balanced over its sign classes (-, 0, +: each "
                                              "class present weighs alike), which teaches the core rare rewards",
                                         traced=True)
    multistep: str = _opt("1", "offline runs: multi-step training: K feeds the model its own prediction between "
                               "real frames every K steps of a chunk (1: teacher forcing); 'K1,K2,...' a "
                               "curriculum over equal parts of --steps (Oh et al. 2015: 1,3,5)")
    mirror_streams: bool = _opt(False, "offline runs on the built-in game: the second half of the B streams sees its "
                                       "episodes mirrored left to right, the turn buttons swapped (the game's "
                                       "symmetry: no game frame more; a model cannot learn to prefer one turn)")
    lookahead_steps: int = _opt(0, "controller variants, offline and the replay learners: K imagined steps from real "
                                   "states, each scored against the real frame and reward, with reward, continuation "
                                   "and value heads on the model's state (cdrl.training.lookahead; 0: off; TD-MPC2 "
                                   "trains 3, MuZero 5)")
    lookahead_stride: int = _opt(0, "the look-ahead starts from every this-many-th real step of a chunk (0: K, which "
                                    "costs about one more pass over the chunk)")
    imagined_frame_weight: float = _opt(1.0, "look-ahead: weight of the imagined frames' BCE (the imagined "
                                             "rewards' squared error takes reward_weight)", traced=True)
    imagined_reward_balanced_weight: float = _opt(0.0, "look-ahead, reward variants: weight of the imagined rewards' "
                                                       "squared error balanced over its sign classes (as "
                                                       "reward_balanced_weight, at every imagined step: the "
                                                       "imagination must carry the coming pellet)", traced=True)
    reward_head_weight: float = _opt(1.0, "look-ahead: weight of the reward head's two-hot cross-entropy",
                                     traced=True)
    cont_weight: float = _opt(1.0, "look-ahead: weight of the continuation head's BCE", traced=True)
    value_weight: float = _opt(1.0, "look-ahead: weight of the value head's two-hot cross-entropy against "
                                    "lambda-returns (gamma, gae_lambda)", traced=True)
    head_grad: float = _opt(0.01, "look-ahead: scale of the heads' gradient into the model (the heads themselves "
                                  "learn at full scale, by Adam at ctrl_lr)", traced=True)
    value_backup: str = _opt("lambda", "look-ahead: the value's targets: 'lambda', lambda-returns of the data's own "
                                       "buttons; 'max', Peng's Q(lambda), each step bootstrapped on the best of the "
                                       "eight buttons pressed with the next real frame (the planner's one-step "
                                       "scores)")
    frame_value_weight: float = _opt(0.0, "look-ahead: weight of a value head on the model's predicted next frame "
                                          "(a CNN of its own; 0: no such head); the planner values its plans' "
                                          "last predicted frame with it")
    advantage_weight: float = _opt(0.0, "look-ahead: weight of an advantage head A(h) on the model's state, its "
                                        "target the return less the mean of the eight buttons' values (0: no such "
                                        "head); the planner then ranks one-step plans by it")
    value_target_decay: float = _opt(0.98, "look-ahead: per update, the value's target copy keeps this share of "
                                           "itself and takes the rest from the value head", traced=True)


@dataclasses.dataclass(frozen=True)
class ControlOptions:
    """The learner and its numbers (`cdrl learners`)."""

    learner: str = _opt("thesis_ascent", "how a controller variant learns to control (`cdrl learners`): "
                                         "thesis_ascent (the thesis: reward ascent through the real chunk), "
                                         "imagined_ascent (ascent through imagined rollouts), imagination_ac (an "
                                         "actor-critic in imagination), one_step_q (the buttons' values one model "
                                         "step ahead, from real returns), onpolicy_ac (an actor-critic on the "
                                         "model's states of the chunk just played, from its real rewards), "
                                         "mpc_planner (plans each step through the model); the last five keep "
                                         "a replay buffer. world_model: no controller, the world "
                                         "model learns offline on recorded episodes, a start for --init-from. ppo: "
                                         "model-free, from the same frames, whatever the variant. Old names: "
                                         "rollout, imagine, critic, value, real, none")
    init_from: str = _opt("", "a run directory whose trained world model (its newest good checkpoint; same variant "
                              "and preset) this run starts from, with its input normalisation ('': a fresh model)")
    scope: str = _opt("controller", "thesis_ascent and onpolicy_ac: parameters the reward ascent or the actor-critic "
                                    "may change: controller or all")
    ascent: float = _opt(0.1, "model-based learners: lambda, the weight of the controller's objective", traced=True)
    noise_std: float = _opt(0.3, "model-based learners: exploration: the std of the noise on the controller's actions "
                                 "(thesis_ascent), the chance a button is drawn uniformly (the replay learners)",
                            traced=True)
    noise_decay: float = _opt(0.999, "model-based learners: per-update decay factor of the exploration", traced=True)
    warmup_steps: int = _opt(100, "model-based learners: updates of pure model learning before the controller's "
                                  "objective", traced=True)
    replay: int = _opt(64, "replay learners: chunks kept in the replay buffer")
    model_updates: int = _opt(4, "replay learners: model updates per collected chunk")
    horizon: int = _opt(15, "imagined_ascent and imagination_ac: imagined steps; mpc_planner: the steps of "
                                "each plan")
    ctrl_lr: float = _opt(3e-4, "replay learners: Adam learning rate of the controller and the critic; the "
                                "look-ahead heads' too", traced=True)
    gamma: float = _opt(0.99, "discount of future reward", traced=True)
    gae_lambda: float = _opt(0.95, "ppo: lambda of generalised advantage estimation; the replay learners: of the "
                                   "lambda-returns", traced=True)
    clip_eps: float = _opt(0.2, "ppo and onpolicy_ac: clip range of the probability ratio (and of ppo's value)",
                           traced=True)
    value_coef: float = _opt(0.5, "ppo: weight of the value loss", traced=True)
    entropy_coef: float = _opt(0.01, "ppo and the replay learners: weight of the entropy bonus", traced=True)
    ppo_epochs: int = _opt(4, "ppo and onpolicy_ac: passes over each rollout")
    critic_plan: str = _opt("off", "onpolicy_ac: one step of look-ahead through the model. Each step the eight button "
                                   "combinations are scored Q(a) = predicted reward + gamma x the critic's value of "
                                   "the model's state after a, and the buttons pressed are argmax log pi(a) + "
                                   "plan_weight x Q(a). off: the controller alone; eval: the noise-free policy "
                                   "(evaluations, test games); always: the games of training too, drawn from "
                                   "pi(a) exp(plan_weight x Q(a))")
    plan_weight: float = _opt(30.0, "onpolicy_ac with critic_plan: kappa, the weight of Q(a) against the "
                                     "controller's log-probability", traced=True)
    ppo_minibatches: int = _opt(4, "ppo: minibatches per pass (batch x unroll must divide by it)")


@dataclasses.dataclass(frozen=True)
class ScheduleOptions:
    """How long a run trains, on what shape of chunks, and what it records."""

    recipe: str = _opt("tuned", "training recipe filling the options it names: tuned or thesis (fast: the old name "
                                "of tuned)")
    unroll: int = _recipe_opt("truncated-BPTT length T")
    batch: int = _recipe_opt("independent episode streams per step B")
    steps: int = _opt(1000, "training steps (chunks)")
    seed: int = _opt(0, "seed of the parameters and the data order", traced=True)
    devices: int = _opt(1, "devices to spread over (0: every device of every process): a run's B streams "
                           "(data parallel; B a multiple of it), or a sweep's configurations")
    checkpoint_every: int = _opt(200, "steps between checkpoints")
    keep_checkpoints: int = _opt(3, "how many checkpoints to keep")
    eval_every: int = _opt(250, "steps between held-out evaluations (0: only at the end)")
    eval_episodes: int = _opt(4, "held-out episodes per evaluation (learners that play: games per policy)")
    tensorboard: bool = _opt(True, "also write TensorBoard event files to RUN_DIR/tb (view: tensorboard --logdir runs)")


# Section name -> its options, in the order `config.json` lists them.
SECTIONS: dict[str, type] = {"game": GameOptions, "model": ModelOptions, "optim": OptimOptions,
                             "loss": LossOptions, "control": ControlOptions, "schedule": ScheduleOptions}
CONTROL = ControlOptions()

# option -> value, per recipe. Options not listed keep their field default.
RECIPES: dict[str, dict[str, object]] = {
    "thesis": {
        "optimizer": "sgd", "lr": 0.1, "momentum": 0.9, "b2": 0.999, "weight_decay": 0.0, "grad_clip": 0.0,
        "lr_schedule": "constant", "lr_warmup": 0, "batch": 1, "unroll": 32, "obs_norm": "none",
        "fc_init_gain": 1.0, "reward_weight": 0.1,
    },
    "tuned": {
        "optimizer": "sgd", "lr": 2.0, "momentum": 0.9, "b2": 0.999, "weight_decay": 0.0, "grad_clip": 0.0,
        "lr_schedule": "constant", "lr_warmup": 0, "batch": 4, "unroll": 8, "obs_norm": "data",
        "fc_init_gain": 5.0, "reward_weight": 0.1,
    },
}
# Learners of family "ascent" train online against the game on their own actions; their reward
# terms make large steps diverge (measured: lr 1, or an FC gain of 5, blow up within 10
# updates), so `tuned` keeps the controller experiments' rate, streams and horizon for them.
ONLINE_OVERRIDES: dict[str, dict[str, object]] = {
    "thesis": {},
    "tuned": {"lr": 0.1, "batch": 8, "unroll": 16, "fc_init_gain": 1.0},
}
# With a replay buffer the model learns teacher-forced, as offline, so `tuned` takes the offline
# rate of the closed loops (lr 1; lr 2 diverges online as offline) and its FC gain; the reward
# term's weight is 0.01 (at lr 1 and weight 0.1 the reward head's squared error grows without
# bound within 5 updates).
REPLAY_OVERRIDES: dict[str, dict[str, object]] = {
    "thesis": {},
    "tuned": {"lr": 1.0, "fc_init_gain": 5.0, "reward_weight": 0.01},
}
# A controller variant's world model trained offline (learner world_model) learns its frames
# alone: with one SGD optimiser for everything its reward term's gradient kills the core
# (measured, final_proposal, small preset, lr 1: at weight 0.01 the reward error jumps from
# 0.15 to 7 at step 1 and every LSTM and encoder gradient is 0 by step 50, the held-out excess
# ratio stuck at 1.46; at weight 0 it reaches 0.74 in 4000 steps). Its reward head is left to
# the online run, which steps it with its own optimiser (`cdrl.learners.replay_base`).
OFFLINE_WORLD_MODEL: dict[str, dict[str, object]] = {"thesis": {}, "tuned": {"reward_weight": 0.0}}
# What each family of learners takes over its recipe's numbers.
FAMILY_OVERRIDES: dict[str, dict[str, dict[str, object]]] = {
    "ascent": ONLINE_OVERRIDES,
    "replay": {name: {**ONLINE_OVERRIDES[name], **REPLAY_OVERRIDES[name]} for name in RECIPES},
}
# Learners without a world model, whatever the recipe: PPO's usual numbers (Adam lr 2.5e-4,
# gradient norm clipped at 0.5, 16 games x 32 steps per update).
AGENT_RECIPE: dict[str, object] = {
    "optimizer": "adam", "lr": 2.5e-4, "momentum": 0.9, "b2": 0.999, "weight_decay": 0.0, "grad_clip": 0.5,
    "lr_schedule": "constant", "lr_warmup": 0, "batch": 16, "unroll": 32, "obs_norm": "data", "fc_init_gain": 1.0,
    "reward_weight": 0.0,
}
DEFAULT_RECIPE = "tuned"


def section_of() -> dict[str, str]:
    """Option name -> the name of its section."""
    return {f.name: name for name, cls in SECTIONS.items() for f in dataclasses.fields(cls)}
