"""The learner interface: a learner written outside the library, registered with one line, runs
through `cdrl train`, checkpoints and resumes exactly; old learner names still load."""
import json

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdrl import learners
from cdrl.cli import main as cli_main
from cdrl.learners.api import Learner, collect
from cdrl.learners.game_batch import reset_games
from cdrl.runs.config import RunConfig, saved_config
from cdrl.training.optim import init_opt_state
from cdrl.training.step import guarded_update


@flax.struct.dataclass
class BiasState:
    params: dict
    opt_state: object
    games: object
    key: jax.Array


class ButtonBias(Learner):
    """A toy model-free learner: each button pressed with probability sigmoid(b), the three
    biases b learnt by REINFORCE on the step's reward."""

    name = "button_bias"
    row = "button_bias"
    has_world_model = False

    @classmethod
    def from_run(cls, cfg, model, game, env_params):
        return cls(model, game, (cfg.batch, cfg.unroll), cfg.opt_hparams(), env_params)

    def init(self, key):
        params = {"buttons": {"bias": jnp.zeros(3)}}
        k_env, k_run = jax.random.split(key)
        return BiasState(params, init_opt_state(self.hp, params),
                         reset_games(self.game, self.env_params, k_env, self.config[0], self.arch), k_run)

    def act(self, state, obs, key):
        p = jax.nn.sigmoid(state.params["buttons"]["bias"])
        action = (jax.random.uniform(key, obs.frames.shape[:1] + (3,)) < p).astype(jnp.float32)
        return state, action, {}

    def update(self, state, batch):
        adv = batch["reward"] - jnp.mean(batch["reward"])

        def loss(params):
            logits = params["buttons"]["bias"]
            a = batch["action"]
            logp = jnp.sum(a * jax.nn.log_sigmoid(logits) + (1 - a) * jax.nn.log_sigmoid(-logits), axis=-1)
            return -jnp.mean(logp * adv)

        value, grads = jax.value_and_grad(loss)(state.params)
        params, opt_state, guard = guarded_update(self.hp, jnp.asarray(1e3), state.params, state.opt_state, grads,
                                                  value)
        metrics = {"loss": value, "terms": {"reinforce": value}, **guard, "reward": jnp.mean(batch["reward"]),
                   "episodes": jnp.sum(batch["done"]), "return_sum": jnp.sum(batch["finished_return"]),
                   "length_sum": jnp.sum(batch["finished_length"]), "action_mean": jnp.mean(batch["action"], (0, 1))}
        return state.replace(params=params, opt_state=opt_state), metrics

    def train_step(self, state):
        return self.update(*collect(self, state, self.config[1]))

    def policy(self, state):
        def init(key, params):
            return jnp.zeros(())

        def step(key, s, obs, params):
            return (params["buttons"]["bias"] > 0).astype(jnp.float32), s

        return init, step, state.params

    def watched(self, state):
        return state.params


@pytest.fixture
def button_bias():
    learners.register(ButtonBias)
    yield
    learners.LEARNERS.pop(ButtonBias.name)


def _train(run_dir, *extra):
    args = ["train", "--run-dir", str(run_dir), "--learner", "button_bias", "--preset", "tiny", "--batch", "4",
            "--unroll", "8", "--optimizer", "sgd", "--lr", "0.5", "--obs-norm", "none", "--eval-every", "0",
            "--eval-episodes", "1", "--episode-steps", "20", "--checkpoint-every", "2", "--no-tensorboard",
            "--no-compile-cache", *extra]
    assert cli_main(args) == 0


def _losses(run_dir):
    return [json.loads(line)["loss"] for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def test_a_registered_learner_trains_checkpoints_and_resumes_exactly(button_bias, tmp_path):
    """Its module (here, this file) and one `register` line: `cdrl train --learner` runs it, its
    policy is scored against the references, and a run stopped at step 3 and resumed to 4
    logs the same numbers as a run of 4 steps straight."""
    _train(tmp_path / "straight", "--steps", "4")
    _train(tmp_path / "stopped", "--steps", "3")
    assert cli_main(["train", "--resume", str(tmp_path / "stopped"), "--steps", "4", "--no-compile-cache"]) == 0
    straight, resumed = _losses(tmp_path / "straight"), _losses(tmp_path / "stopped")
    assert len(straight) == 4 and np.all(np.isfinite(straight))
    np.testing.assert_array_equal(resumed, straight)
    config = json.loads((tmp_path / "stopped" / "config.json").read_text())
    assert config["control"]["learner"] == "button_bias"
    evals = [json.loads(line) for line in (tmp_path / "straight" / "eval.jsonl").read_text().splitlines()]
    assert {"button_bias", "never_accelerate"} <= set(evals[-1]["policies"])


def test_a_learner_name_is_taken_once():
    with pytest.raises(ValueError, match="'critic' is taken"):
        learners.register(type("Other", (ButtonBias,), {"name": "critic"}))
    with pytest.raises(ValueError, match="unknown learner 'nope'"):
        RunConfig(learner="nope")


@pytest.mark.parametrize("old, new", [({"controller": "real"}, "onpolicy_ac"), ({"controller": "rollout"}, "thesis_ascent"),
                                      ({"controller": "imagine"}, "imagined_ascent"),
                                      ({"controller": "critic"}, "imagination_ac"), ({"controller": "value"}, "one_step_q"),
                                      ({"controller": "none"}, "world_model"), ({"variant": "ppo"}, "ppo")])
def test_old_learner_names_load(old, new):
    """A config.json written before the learners had names (`controller`, `variant` ppo) loads
    with the learner's name, and the same resolved numbers as the new name gives."""
    variant = {} if "variant" in old else {"variant": "final_proposal"}
    cfg = saved_config({"recipe": "fast", **variant, **old})
    assert cfg.learner == new
    fresh = RunConfig(recipe="fast", learner=new, **variant)
    assert cfg == fresh
