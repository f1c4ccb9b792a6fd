"""The privileged policy plays while a world model follows it: what the probes of a world model's
state (`steering_probe.py`, `imagination_probe.py`) play on.

A share `explore` of the privileged policy's steps are random turns instead
(`envs.policies.random_turns_instead`), so that the play holds recoveries. The model is
teacher-forced as a controller run acts (`cdrl.learners.replay_base`) and as recorded data sets hold
their steps: at step t it takes the frame o_t and the buttons executed at o_t, so its state after
the step has seen a_t and predicts o_{t+1} and r_{t+1}.
"""
from __future__ import annotations


def follow_step(variant, params, game, env_params, explore: float):
    """The body of a `jax.lax.scan` over the steps of one game. Its carry is `start(...)`'s;
    per step it gives h_t (the model's features after the step), the privileged buttons at o_t,
    whether the game was on at o_t, and the model's input frame o_t `[H, W]`. After the step the
    carry holds the game at o_{t+1}, the model's state after (o_t, a_t) and its prediction õ_{t+1}
    (`[1, H, W]`; for a variant without a decoder, the last one given)."""
    import jax
    import jax.numpy as jnp

    from cdrl.data.frames import model_obs
    from cdrl.models.base import StepInput
    from envs.policies import privileged_policy, random_turns_instead

    privileged = privileged_policy(game)

    def body(c, _):
        state, obs, carry, first, key, alive, pred = c
        key, k_policy, k_explore, k_env = jax.random.split(key, 4)
        label, _ = privileged.step(k_policy, None, obs, state, env_params)
        executed = random_turns_instead(k_explore, label, explore)
        frame = model_obs(obs, variant.arch)[None]
        carry, out = variant.step(params, carry, StepInput(obs=frame, action=executed[None], is_first=first))
        pred = jax.nn.sigmoid(out["logits"]) if "logits" in out else pred
        obs, state, _, term, trunc, _ = game.step(k_env, state, executed, env_params)
        nxt = (state, obs, carry, jnp.zeros((1,), bool), key, alive & ~(term | trunc), pred)
        return nxt, (variant.features(carry)[0], label, alive, frame[0])

    return body


def start(variant, game, env_params, key):
    """The carry `follow_step`'s body starts a game from: the game reset by `key`'s first half,
    the model's initial state, the rest of the key for the steps."""
    import jax
    import jax.numpy as jnp

    k_reset, k_run = jax.random.split(key)
    obs, state = game.reset(k_reset, env_params)
    size = variant.arch.image_size
    return (state, obs, variant.init_carry(1), jnp.ones((1,), bool), k_run, jnp.array(True),
            jnp.zeros((1, size, size), jnp.float32))
