"""The controller study: model-based controllers, PPO at the same and at ten times the game
frames, and the reference policies, on the same held-out games of the built-in game.

Every configuration (`CONFIGS`) is an ordinary run (`cdrl.runs.train.train_run`), trained once
per seed (a seed sets the initialisation, the exploration and the training games), scored
`evals` times during training and at the end on the same held-out games (seeds 10000, 10001,
...; `cdrl.evaluation.play.compare_policies`), noise-free: a controller executes ã, PPO its
greedy buttons. The reference policies play the same games once: they do not learn.

  critic        final_proposal, an actor-critic in imagination (`--controller critic`)
  imagine       final_proposal, reward ascent through imagined rollouts (`--controller imagine`)
  rollout       final_proposal, the thesis's reward ascent through the real chunk, scope controller
  rollout-all   the same, scope all (the thesis's literal wording: is reward hallucinated?)
  critic-open   reward_prediction (open loop on observations), as `critic`: does closed loop − help?
  real-pre      on `critic-pre`'s world model, an actor-critic on the real states of the chunks played,
                from their real rewards (`--controller real`; exploration 0.05, no warm-up)
  real-pre-all  the same with scope all: its gradient shapes the world model's core and encoder too
  real-pre-all-open  `real-pre-all` on reward_prediction (open loop on observations)
  real-pre-all-open-bal  the same, its pre-training also teaching the core the reward balanced over
                its sign classes (`reward_balanced_weight` 0.003: a pellet eaten weighs as much as none)
  real-plan-eval  `real-pre-all-open-bal` whose noise-free policy looks one step ahead through the
                model (`--critic-plan eval`: each button combination scored by the predicted reward
                and the critic's value after it, tilting the controller's buttons)
  real-plan     the same, the games of training played so too (`--critic-plan always`)
  real-pre-all-bal  `real-pre-all` pre-trained with the same balanced term: against
                `real-pre-all-open-bal`, does closed loop − help?
  real-all      `real-pre-all` without the pre-training (the model from scratch on Adam, as `critic`)
  critic-pre    `critic` on a world model learnt offline first (`--controller none`, on the data
                the run collects: 60 episodes of uniform-random play) and trained on online
                (`--init-from`); its game frames count the pre-training data's
  critic-pre-bal  `critic` on `real-pre-all-bal`'s world model (the same pre-training): does the
                actor-critic in imagination control where the one on real returns does?
  value-pre     `critic-pre` with the one-step value learner (`--controller value`)
  plan-pre      model-predictive control (`--learner mpc_planner`, 5-step plans, the value at the end)
                on a world model pre-trained with the look-ahead heads (`--lookahead-steps 3`)
  plan-pre-bal  the same, its pre-training also teaching the balanced reward (as `-bal` above)
  plan-pre-clip  the same on the world model's best look-ahead training (clipped, value at gamma 0.9)
  plan1-pre-clip  the same with one-step plans: each button combination's reward and value after
                the real frame, nothing imagined
  plan-pre-bal-mirror  the same, half of its pre-training's streams seen in a mirror (`--mirror-streams`)
  imagine-look-pre-bal, critic-look-pre-bal  `imagine` and `critic` on `plan-pre-bal`'s world model
                (5 imagined steps and the value head's value at the end)
  ppo           PPO at the same game frames; ppo-10x at ten times them; ppo-8x at eight (384 000
                frames at the 48k budget)

Runs live under a work directory, one per configuration and seed (`NAME/seedS`); a finished
run is read back, an unfinished one resumed, so an experiment continues where it stopped.

Reported per configuration (`configs[name]`): its options, the game frames of a run, per seed
the final held-out `return` (mean over the games, with their 95 % CI), `length` (survival in
steps), the learning curve, the seconds it took, and for models with a reward head its fit to
the reward of its own held-out play (`reward_fit`: correlation and R²), its predicted and real
reward per step and its next-frame excess ratio over the last quarter of training; across seeds
the mean, standard deviation and 95 % CI of each (`cdrl.evaluation.stats.across`).
`references` holds the reference policies' rows (a CI over the games: no seed to vary).

Run from the repository root. It prints a table and ends with one JSON line (`--out FILE` also
writes it there, after every configuration with `"partial": true` until the last). `--full` is
the committed budget (small preset, 38 400 game frames per run, 5 seeds, 64 held-out games of
at most 200 steps; about 5 hours on 2 cores); `--quick` is a smoke test:

    .venv/bin/python experiments/controller/study.py --full --work-dir notebooks/runs/full/03_controller \\
        --out experiments/controller/results/controller.json --figure experiments/controller/results/controller.png

`--merge A.json B.json ...` runs nothing: it pools result files of the same experiment run in
several invocations (other seeds, other configurations; `merge` checks that they share the
budget and the held-out games) and recomputes the across-seed figures:

    .venv/bin/python experiments/controller/study.py --merge seeds01.json seed2.json --out result.json

Notebook 03 runs the same experiment on the same work directory. LOG.md beside this file holds
the questions asked of it, the commands and the answers.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Sequence

import jax
import numpy as np
import scipy.stats

from cdrl import learners
from cdrl.evaluation.play import EVAL_SEED, TEST_SEED, compare_policies, model_fit
from cdrl.evaluation.stats import across
from cdrl.models import make_variant
from cdrl.options import PRESET_ALIASES
from cdrl.runs.config import RunConfig, upgrade
from cdrl.runs.online import restore_learner
from cdrl.runs.rundir import RunDir
from cdrl.runs.sources import load_episodes
from cdrl.runs.train import train_run
from envs.slither import canonical_level

if not __package__:  # run as a file, not with -m: the repository root on the path (benchmarks/, experiments/)
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

LOOK = {"horizon": 5, "lookahead_steps": 3, "head_grad": 1e-4}
LOOK_PRETRAIN = {"lookahead_steps": 3, "head_grad": 1e-4}
LOOK_PRETRAIN_BAL = {"variant": "final_proposal", "learner": "world_model", **LOOK_PRETRAIN,
                     "reward_balanced_weight": 0.003}
# The world model's best look-ahead training (experiments/world_models/LOG.md): the balanced reward
# on the real and imagined steps, the model's gradient norm clipped at 0.05, the heads' gradient
# into it at 1e-3, and a value discounted at 0.9 (about the 15 steps a plan is judged over).
LOOK_CLIP = {"lookahead_steps": 3, "head_grad": 1e-3, "grad_clip": 0.05, "gamma": 0.9,
             "reward_balanced_weight": 0.003, "imagined_reward_balanced_weight": 0.003}

REAL_OPEN_BAL = {"variant": "reward_prediction", "learner": "onpolicy_ac", "scope": "all", "noise_std": 0.05,
                 "warmup_steps": 0, "pretrain": {"variant": "reward_prediction", "learner": "world_model",
                                                 "reward_balanced_weight": 0.003}}

# name -> options of the run (RunConfig fields) besides the budget's; `frames_factor` scales
# the budget's game frames; `pretrain` first trains the world model offline for the budget's
# `pretrain_steps` (RunConfig fields of that run).
CONFIGS: dict[str, dict] = {
    "critic": {"variant": "final_proposal", "learner": "imagination_ac", "optimizer": "adam", "lr": 1e-3},
    "imagine": {"variant": "final_proposal", "learner": "imagined_ascent", "optimizer": "adam", "lr": 1e-3},
    "rollout": {"variant": "final_proposal", "learner": "thesis_ascent", "scope": "controller"},
    "rollout-all": {"variant": "final_proposal", "learner": "thesis_ascent", "scope": "all"},
    "critic-open": {"variant": "reward_prediction", "learner": "imagination_ac", "optimizer": "adam", "lr": 1e-3},
    "critic-pre": {"variant": "final_proposal", "learner": "imagination_ac",
                   "pretrain": {"variant": "final_proposal", "learner": "world_model"}},
    "value-pre": {"variant": "final_proposal", "learner": "one_step_q", "gamma": 0.95, "entropy_coef": 0.05,
                  "pretrain": {"variant": "final_proposal", "learner": "world_model"}},
    "real-pre": {"variant": "final_proposal", "learner": "onpolicy_ac", "noise_std": 0.05, "warmup_steps": 0,
                 "pretrain": {"variant": "final_proposal", "learner": "world_model"}},
    "real-pre-all": {"variant": "final_proposal", "learner": "onpolicy_ac", "scope": "all", "noise_std": 0.05,
                     "warmup_steps": 0, "pretrain": {"variant": "final_proposal", "learner": "world_model"}},
    "real-pre-all-open": {"variant": "reward_prediction", "learner": "onpolicy_ac", "scope": "all", "noise_std": 0.05,
                          "warmup_steps": 0, "pretrain": {"variant": "reward_prediction", "learner": "world_model"}},
    "real-pre-all-open-bal": REAL_OPEN_BAL,
    # `real-pre-all-open-bal` looking one step ahead through its model: each button combination
    # scored by the predicted reward and the critic's value after it, tilting the controller.
    "real-plan-eval": {**REAL_OPEN_BAL, "critic_plan": "eval", "plan_weight": 30.0},
    "real-plan": {**REAL_OPEN_BAL, "critic_plan": "always", "plan_weight": 30.0},
    "real-pre-all-bal": {"variant": "final_proposal", "learner": "onpolicy_ac", "scope": "all", "noise_std": 0.05,
                         "warmup_steps": 0, "pretrain": {"variant": "final_proposal", "learner": "world_model",
                                                         "reward_balanced_weight": 0.003}},
    "critic-pre-bal": {"variant": "final_proposal", "learner": "imagination_ac",
                       "pretrain": {"variant": "final_proposal", "learner": "world_model", "reward_balanced_weight": 0.003}},
    "real-all": {"variant": "final_proposal", "learner": "onpolicy_ac", "scope": "all", "noise_std": 0.05,
                 "warmup_steps": 0, "optimizer": "adam", "lr": 1e-3},
    # The learners that look ahead, on a world model trained with the look-ahead heads (`LOOK`):
    # model-predictive control, the ascent and the actor-critic in imagination, each with the
    # value at the end of 5 imagined steps. `-bal`: the pre-training teaches the balanced reward too.
    "plan-pre": {"variant": "final_proposal", "learner": "mpc_planner", **LOOK, "noise_std": 0.1, "warmup_steps": 0,
                 "pretrain": {"variant": "final_proposal", "learner": "world_model", **LOOK_PRETRAIN}},
    "plan-pre-bal": {"variant": "final_proposal", "learner": "mpc_planner", **LOOK, "noise_std": 0.1,
                     "warmup_steps": 0, "pretrain": LOOK_PRETRAIN_BAL},
    "plan-pre-bal-mirror": {"variant": "final_proposal", "learner": "mpc_planner", **LOOK, "noise_std": 0.1,
                            "warmup_steps": 0, "pretrain": {**LOOK_PRETRAIN_BAL, "mirror_streams": True}},
    "plan-pre-clip": {"variant": "final_proposal", "learner": "mpc_planner", "horizon": 5, **LOOK_CLIP,
                      "noise_std": 0.1, "warmup_steps": 0,
                      "pretrain": {"variant": "final_proposal", "learner": "world_model", **LOOK_CLIP}},
    "plan1-pre-clip": {"variant": "final_proposal", "learner": "mpc_planner", "horizon": 1, **LOOK_CLIP,
                       "noise_std": 0.1, "warmup_steps": 0,
                       "pretrain": {"variant": "final_proposal", "learner": "world_model", **LOOK_CLIP}},
    "imagine-look-pre-bal": {"variant": "final_proposal", "learner": "imagined_ascent", **LOOK,
                             "pretrain": LOOK_PRETRAIN_BAL},
    "critic-look-pre-bal": {"variant": "final_proposal", "learner": "imagination_ac", **LOOK,
                            "pretrain": LOOK_PRETRAIN_BAL},
    "ppo": {"learner": "ppo"},
    "ppo-10x": {"learner": "ppo", "frames_factor": 10},
    "ppo-8x": {"learner": "ppo", "frames_factor": 8},  # 384 000 frames at the 48k budget
}


@dataclasses.dataclass(frozen=True)
class Budget:
    """How much every run of the experiment gets: the preset, the game frames of training,
    held-out games per evaluation and their step cap, evaluations per run, the model-based
    runs' updates before their controller learns, B x T of model-based runs and of PPO, the
    steps of a world model's offline pre-training (B 4 x T 8, the `tuned` recipe's), the
    game's level (`envs.slither.LEVELS`) and the max filter the frames are shrunk after.
    `test_games`: after training, each run's final policy plays that many test games (seeds
    `TEST_SEED` and up, never used for a choice; 0: none). `pretrain_in_frames`: `frames` is
    every game frame a run uses, its pre-training data's included (the online part gets the
    rest); otherwise the online part gets `frames` and the data comes on top."""

    preset: str
    frames: int
    eval_episodes: int
    episode_steps: int
    evals: int
    warmup_steps: int
    model_shape: tuple[int, int] = (8, 16)
    ppo_shape: tuple[int, int] = (16, 32)
    pretrain_steps: int = 8000
    level: str = "thesis"
    max_filter: int = 1
    test_games: int = 0
    pretrain_in_frames: bool = False


BUDGETS = {
    "full": Budget("small", 38_400, 64, 200, 4, 50),
    "default": Budget("small", 6_400, 16, 200, 2, 10),
    "tiny": Budget("tiny", 64, 3, 20, 1, 1, model_shape=(4, 4), ppo_shape=(4, 4), pretrain_steps=4),
    # Every frame counted, pre-training data included; final figures from 128 test games.
    "48k": Budget("small", 48_000, 64, 200, 4, 50, test_games=128, pretrain_in_frames=True),
    "192k": Budget("small", 192_000, 64, 200, 8, 50, test_games=128, pretrain_in_frames=True),
}


def pretrain_config(name: str, budget: Budget, seed: int) -> RunConfig | None:
    """The offline pre-training run of configuration `name` for `seed` (None: it has none)."""
    if "pretrain" not in CONFIGS[name]:
        return None
    return RunConfig(preset=budget.preset, max_filter=budget.max_filter, steps=budget.pretrain_steps, seed=seed,
                     eval_every=max(1, budget.pretrain_steps // budget.evals), checkpoint_every=budget.pretrain_steps,
                     eval_episodes=6, tensorboard=False, level=budget.level, **CONFIGS[name]["pretrain"])


def config_of(name: str, budget: Budget, seed: int, init_from: Path | None = None, data_frames: int = 0) -> RunConfig:
    """The run of configuration `name` for `seed` at `budget` (from the world model of the
    run in `init_from`, its pre-training, whose data held `data_frames` game frames)."""
    options = dict(CONFIGS[name])
    factor = options.pop("frames_factor", 1)
    options.pop("pretrain", None)
    batch, unroll = budget.ppo_shape if options.get("learner") == "ppo" else budget.model_shape
    online = budget.frames * factor - (data_frames if budget.pretrain_in_frames else 0)
    if online < batch * unroll:
        raise ValueError(f"configuration {name!r}: its pre-training data's {data_frames} game frames leave "
                         f"{online} of the budget's {budget.frames * factor}, less than one chunk")
    steps = online // (batch * unroll)
    every = max(1, steps // budget.evals)
    options = {"warmup_steps": budget.warmup_steps, **options}
    return RunConfig(preset=budget.preset, max_filter=budget.max_filter, batch=batch, unroll=unroll, steps=steps,
                     seed=seed, eval_every=every,
                     checkpoint_every=every, eval_episodes=budget.eval_episodes, episode_steps=budget.episode_steps,
                     tensorboard=False, init_from=str(init_from or ""), level=budget.level, **options)


def train_or_read(cfg: RunConfig, run_dir: Path) -> float:
    """Train `cfg` in `run_dir`, resume it if it is unfinished, or read it back if it is
    finished (its evaluation at the last step is there). Returns the seconds spent."""
    run = RunDir(run_dir)
    t0 = time.perf_counter()
    finished = run.has_run() and any(r["step"] == cfg.steps for r in run.evals.read())
    if run.has_run() and not finished:
        train_run(None, run_dir, resume=True, progress=False)
    elif not finished:
        train_run(cfg, run_dir, progress=False)
    return time.perf_counter() - t0


def seed_result(run_dir: Path, budget: Budget) -> dict:
    """A finished run's figures: the final held-out `return` (with its CI over the games),
    `length` (survival), the learning curve ([game frames, held-out return] after each
    evaluation), the reference rows, and for a reward head its fit on its own held-out play."""
    run = RunDir(run_dir)
    cfg = run.read_config()
    evals = [r for r in run.evals.read() if r.get("split") == "play"]
    name = learners.learner_class(cfg.learner).row  # the learned policy's row in the table
    final = evals[-1]["policies"]
    frames = cfg.batch * cfg.unroll
    out = {"return": final[name]["mean_return"], "ci95_over_games": final[name]["ci95"],
           "length": final[name]["mean_length"], "frames": cfg.steps * frames,
           "curve": [[r["step"] * frames, r["policies"][name]["mean_return"]] for r in evals],
           "references": {k: v for k, v in final.items() if k != name}}
    if budget.test_games:
        _, learner, state = restore_learner(run)
        rows = compare_policies(learner.game, learner.env_params, {name: learner.policy(state)}, budget.test_games,
                                budget.episode_steps, seed=TEST_SEED)
        out["test"] = {"return": rows[name]["mean_return"], "ci95_over_games": rows[name]["ci95"],
                       "length": rows[name]["mean_length"], "references": {k: v for k, v in rows.items() if k != name}}
    if cfg.kind == "online" and make_variant(cfg.variant, cfg.arch).predicts_reward:
        _, program, state = restore_learner(run)
        seeds = np.arange(EVAL_SEED, EVAL_SEED + budget.eval_episodes)
        fit = model_fit(program.model, program.world_model(state), program.game, program.env_params, seeds,
                        budget.episode_steps)
        out["excess_ratio_held_out"] = fit.pop("excess_ratio")
        out["reward_fit"] = fit
        tail = run.metrics.read()[-max(1, cfg.steps // 4):]
        out["predicted_reward_per_step"] = float(np.mean([r["terms"]["pred_reward"] for r in tail]))
        out["real_reward_per_step"] = float(np.mean([r["reward"] for r in tail]))
        out["excess_ratio_last_quarter"] = float(np.nanmean([r.get("excess_ratio", np.nan) for r in tail]))
    return out


def pretrain_result(run_dir: Path) -> dict:
    """A pre-training run's figures: its data's game frames (training episodes: their frames
    are what the world model saw), steps, and held-out excess ratio at the end."""
    run = RunDir(run_dir)
    cfg = run.read_config()
    train, _ = load_episodes(cfg, run.data_cache)
    final = [r for r in run.evals.read() if r["step"] == cfg.steps][-1]
    return {"pretrain": {"data_frames": int(sum(len(train[i].frames) for i in range(len(train)))),
                         "steps": cfg.steps, "excess_ratio": final["excess_ratio"]}}


def run_experiment(names: Sequence[str], budget: Budget, seeds: Sequence[int], work: Path,
                   on_config=None) -> dict:
    """Every configuration of `names` on every seed, under `work`: the results (see the module
    docstring). `on_config(results)` sees the results after each configuration."""
    results = {"budget": {**dataclasses.asdict(budget), "seeds": list(seeds)}, "configs": {},
               "references": None}
    for name in names:
        per_seed = {}
        for seed in seeds:
            run_dir = Path(work) / name / f"seed{seed}"
            pre, pre_dir, pre_wall = pretrain_config(name, budget, seed), None, 0.0
            if pre is not None:
                pre_dir = Path(work) / name / f"pretrain{seed}"
                pre_wall = train_or_read(pre, pre_dir)
            pre_result = pretrain_result(pre_dir) if pre_dir is not None else None
            data_frames = pre_result["pretrain"]["data_frames"] if pre_result else 0
            wall = train_or_read(config_of(name, budget, seed, pre_dir, data_frames), run_dir)
            result = {**seed_result(run_dir, budget), "wall_s": wall + pre_wall}
            if pre_result is not None:  # the pre-training's game frames count too
                result.update(pre_result)
                offset = result["pretrain"]["data_frames"]
                result["frames"] += offset
                result["curve"] = [[f + offset, r] for f, r in result["curve"]]
            per_seed[str(seed)] = result
            # Every seed's programs would stay mapped in this process (about six memory maps each):
            # a whole experiment ran out of the JIT's memory ("LLVM ERROR: Unable to allocate
            # section memory"). The next seed loads them again from the compilation cache.
            jax.clear_caches()
        results["references"] = results["references"] or per_seed[str(seeds[0])]["references"]
        if budget.test_games:
            results["test_references"] = results.get("test_references") or per_seed[str(seeds[0])]["test"].pop(
                "references")
            for result in per_seed.values():
                result["test"].pop("references", None)
        results["configs"][name] = summarise(CONFIGS[name], per_seed)
        pair_with(results, "ppo")
        if on_config is not None:
            on_config(results)
    return results


def summarise(options: dict, per_seed: dict) -> dict:
    """A configuration's row: its options, the first seed's game frames, the per-seed results
    (seed as a string -> `seed_result`'s dict) and the across-seed figures of each."""
    first = next(iter(per_seed.values()))
    row = {"options": options, "frames": first["frames"], "seeds": per_seed,
           "return": across([s["return"] for s in per_seed.values()]),
           "length": across([s["length"] for s in per_seed.values()])}
    for key in ("predicted_reward_per_step", "real_reward_per_step", "excess_ratio_last_quarter",
                "excess_ratio_held_out"):
        if key in first:
            row[key] = across([s[key] for s in per_seed.values()])
    if "reward_fit" in first:
        row["reward_fit"] = {k: across([s["reward_fit"][k] for s in per_seed.values()])
                             for k in ("correlation", "r2")}
    if "test" in first:
        row["test_return"] = across([s["test"]["return"] for s in per_seed.values()])
    return row


def pair_with(results: dict, base: str) -> None:
    """Each configuration's `paired_vs_<base>`: the per-seed differences of its final return
    against configuration `base`'s on the same seeds (test games where the budget plays them,
    else the held-out ones), their mean and 95 % CI. Nothing while `base` has not run."""
    if base not in results["configs"]:
        return
    key = "test_return" if "test_return" in results["configs"][base] else "return"
    theirs = dict(zip(results["configs"][base]["seeds"], results["configs"][base][key]["per_seed"]))
    for name, row in results["configs"].items():
        if name == base or key not in row:
            continue
        mine = dict(zip(row["seeds"], row[key]["per_seed"]))
        common = [s for s in mine if s in theirs]
        if common:
            row[f"paired_vs_{base}"] = {**across([mine[s] - theirs[s] for s in common]), "seeds": common,
                                        "of": key}


def options_now(options: dict) -> dict:
    """A configuration's options as a result file holds them, under today's names (results
    written before the learners had names say `controller` and variant ppo)."""
    now = upgrade({k: v for k, v in options.items() if k != "pretrain"})
    if "learner" in now:
        name = now["learner"] = learners.canonical(now["learner"])
        if name != learners.OFFLINE and not learners.learner_class(name).has_world_model:
            now.pop("variant", None)  # a model-free learner plays whatever the variant
    if "pretrain" in options:
        now["pretrain"] = options_now(options["pretrain"])
    return now


def merge(parts: Sequence[dict]) -> dict:
    """Results of one experiment run in several invocations (other seeds, other configurations)
    as one: the per-seed rows pooled and the across-seed figures recomputed.

    Raises ValueError, naming what differs, unless every part has the same budget (its seeds
    and name aside), the same reference rows (so the same held-out games) and, per
    configuration, the same options; a seed reported by two parts must carry the same result
    in both."""
    if not parts:
        raise ValueError("nothing to merge: no results given")
    for i, part in enumerate(parts):
        missing = [k for k in ("budget", "references", "configs") if k not in part]
        if missing:
            raise ValueError(f"results {i} is not a control experiment's result (no {', '.join(missing)})")
    first = parts[0]

    def budget_of(r):  # the budget's `name` only labels its other fields; read back, tuples are lists
        budget = {"max_filter": 1, **r["budget"]}
        if budget["preset"] in PRESET_ALIASES:  # an old name, written before --max-filter
            budget["preset"], budget["max_filter"] = PRESET_ALIASES[budget["preset"]]
        if "level" in budget:  # a level's old name is its new one
            budget["level"] = canonical_level(budget["level"])
        return json.loads(json.dumps({k: v for k, v in budget.items() if k not in ("seeds", "name")}))

    base = budget_of(first)
    configs: dict[str, tuple[dict, dict]] = {}
    for i, part in enumerate(parts):
        budget = budget_of(part)
        if budget != base:
            diff = sorted(k for k in budget.keys() | base.keys() if budget.get(k) != base.get(k))
            raise ValueError(f"results {i} ran another budget than results 0 (differs in {', '.join(diff)})")
        if part["references"] != first["references"]:
            raise ValueError(f"results {i} scored other held-out games than results 0 (its reference rows differ)")
        for name, row in part["configs"].items():
            options, per_seed = configs.setdefault(name, (options_now(row["options"]), {}))
            if options_now(row["options"]) != options:
                raise ValueError(f"configuration {name!r} of results {i} has other options than before: "
                                 f"{row['options']} against {options}")
            for seed, result in row["seeds"].items():
                if seed in per_seed and per_seed[seed] != result:
                    raise ValueError(f"seed {seed} of configuration {name!r} differs between the results")
                per_seed[seed] = result
    seeds = sorted({int(s) for _, per_seed in configs.values() for s in per_seed})
    out = {"budget": {**first["budget"], "seeds": seeds}, "references": first["references"], "configs": {}}
    if "test_references" in first:
        out["test_references"] = first["test_references"]
    for name, (options, per_seed) in configs.items():
        out["configs"][name] = summarise(options, {s: per_seed[s] for s in sorted(per_seed, key=int)})
    pair_with(out, "ppo")
    warnings = sorted({p["warning"] for p in parts if p.get("warning")})
    if warnings:
        out["warning"] = "; ".join(warnings)
    return out


def format_results(results: dict) -> str:
    """The experiment's table: per configuration the game frames, the final held-out return
    across seeds (mean, 95 % CI) and survival; the reference policies below."""
    b = results["budget"]
    lines = [f"held-out return over {b['eval_episodes']} games of at most {b['episode_steps']} steps, "
             f"across seeds {b['seeds']}: mean [95% CI, Student t]; survival in steps",
             f"{'policy':16s} {'frames':>9s} {'mean':>8s} {'95% CI across seeds':>22s} {'survival':>9s}   per seed"]
    for name, r in results["configs"].items():
        ci = r["return"]["ci95"] or [float("nan")] * 2
        lines.append(f"{name:16s} {r['frames']:9d} {r['return']['mean']:8.3f} [{ci[0]:8.3f}, {ci[1]:8.3f}] "
                     f"{r['length']['mean']:9.1f}   " + ", ".join(f"{v:.2f}" for v in r["return"]["per_seed"]))
        for key, label in (("test_return", "test games"), ("paired_vs_ppo", "paired vs ppo")):
            if key in r:
                tci = r[key]["ci95"] or [float("nan")] * 2
                lines.append(f"  {label:14s} {'':>9s} {r[key]['mean']:8.3f} [{tci[0]:8.3f}, {tci[1]:8.3f}]")
    for label, refs in (("", results["references"]), (" (test)", results.get("test_references"))):
        for name, row in (refs or {}).items():
            lines.append(f"{name + label:16s} {'-':>9s} {row['mean_return']:8.3f} [{row['ci95'][0]:8.3f}, "
                         f"{row['ci95'][1]:8.3f}] {row['mean_length']:9.1f}   (95% CI over the games; no seed to vary)")
    return "\n".join(lines)


def curves_figure(results: dict):
    """Held-out return against game frames of training: every configuration's mean over seeds
    with its 95 % CI band, the reference policies as dashed lines."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 5.5))
    ax = fig.subplots()
    for i, (name, r) in enumerate(results["configs"].items()):
        curves = [s["curve"] for s in r["seeds"].values()]
        n = min(len(c) for c in curves)
        frames = np.array([p[0] for p in curves[0][:n]])
        values = np.array([[p[1] for p in c[:n]] for c in curves])
        mean = values.mean(axis=0)
        seeds = f"{len(curves)} seed" + ("s" if len(curves) != 1 else "")
        ax.plot(frames, mean, marker="o", color=f"C{i}", label=f"{name} ({seeds})")
        if len(curves) > 1:
            half = scipy.stats.t.ppf(0.975, len(curves) - 1) * values.std(axis=0, ddof=1) / np.sqrt(len(curves))
            ax.fill_between(frames, mean - half, mean + half, color=f"C{i}", alpha=0.15, linewidth=0)
    for name, row in (results["references"] or {}).items():
        ax.axhline(row["mean_return"], linestyle="--", linewidth=1, color="grey")
        ax.text(1.0, row["mean_return"], f" {name}", transform=ax.get_yaxis_transform(), fontsize=8, va="center")
    ax.set_xscale("log")
    ax.set_xlabel("game frames of training")
    b = results["budget"]
    ax.set_ylabel(f"held-out return ({b['eval_episodes']} games; mean, 95 % CI over seeds)")
    ax.set_title(f"Control on the built-in game (level {b['level']}, preset {b['preset']})")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    return fig


def main(argv=None) -> int:
    from benchmarks.common import emit, warn_if_busy

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--full", action="store_true", help="the committed budget (default: a short check)")
    size.add_argument("--quick", action="store_true", help="a smoke test on the tiny preset")
    size.add_argument("--budget", choices=["48k", "192k"], default=None,
                      help="every game frame counted, pre-training data included (48 000 or 192 000), and the final "
                           "figures from 128 test games (seeds 30000 and up)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4], help="training seeds (default: 0-4)")
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS),
                        help="configurations to run, in this order (default: all)")
    parser.add_argument("--level", default="thesis",
                        help="the game's level (envs.slither.LEVELS, or an old name of one; default: thesis)")
    parser.add_argument("--preset", default=None,
                        help="the architecture preset (cdrl.models.PRESETS; default: the budget's, small for --full)")
    parser.add_argument("--max-filter", type=int, default=1,
                        help="side of the max filter the game's frames are shrunk after (default: 1, none)")
    parser.add_argument("--work-dir", default=None, help="where the runs go (default: a temporary directory)")
    parser.add_argument("--out", default=None, help="also write the JSON result to this file")
    parser.add_argument("--figure", default=None, help="draw the learning curves into this PNG file")
    parser.add_argument("--merge", nargs="+", default=None, metavar="FILE",
                        help="run nothing: pool these result files (JSON) into one, the figures across seeds "
                             "recomputed")
    args = parser.parse_args(argv)
    if args.merge:
        return merge_files(args.merge, args.out, args.figure)
    # Every seed of a configuration runs the same programs: compile each once.
    jax.config.update("jax_compilation_cache_dir", os.environ.get("JAX_COMPILATION_CACHE_DIR")
                      or tempfile.mkdtemp(prefix="cdrl-controller-xla-"))
    budget_name = args.budget or ("full" if args.full else "tiny" if args.quick else "default")
    budget = BUDGETS[budget_name]
    budget = dataclasses.replace(budget, level=canonical_level(args.level), preset=args.preset or budget.preset,
                                 max_filter=args.max_filter)
    work = Path(args.work_dir or tempfile.mkdtemp(prefix="cdrl-controller-"))
    load_start = os.getloadavg()[0]

    def partial(results: dict) -> None:
        print(format_results(results), file=sys.stderr, flush=True)
        if args.out:
            emit({**results, "partial": True}, args.out)

    results = run_experiment(args.configs, budget, args.seeds, work, on_config=partial)
    results["budget"]["name"] = "quick" if budget_name == "tiny" else budget_name
    warn_if_busy(results, load_start, os.getloadavg()[0])
    if args.figure:
        from cdrl.analysis.plots import save_figure

        save_figure(curves_figure(results), Path(args.figure))
    emit(results, args.out)
    return 0


def merge_files(paths, out, figure) -> int:
    """`--merge`: the result files in `paths` pooled (`merge`), printed, written to `out` and
    drawn into `figure` where given."""
    from benchmarks.common import emit

    parts = []
    for path in paths:
        try:
            parts.append(json.loads(Path(path).read_text()))
        except (OSError, json.JSONDecodeError) as e:
            raise SystemExit(f"--merge: cannot read the result file {path}: {e}") from None
    try:
        results = merge(parts)
    except ValueError as e:
        raise SystemExit(f"--merge: {e}") from None
    results["merged_from"] = [str(p) for p in paths]
    print(format_results(results), file=sys.stderr, flush=True)
    if figure:
        from cdrl.analysis.plots import save_figure

        save_figure(curves_figure(results), Path(figure))
    emit(results, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
