"""What the learners that train the controller in the model's imagination share: their static
shape and the imagined rollout itself."""
from __future__ import annotations

import dataclasses

import jax

from cdrl.learners.replay_base import ReplayConfig, draw_buttons
from cdrl.models.base import Variant
from cdrl.options import CONTROL


@dataclasses.dataclass(frozen=True)
class ImaginationConfig(ReplayConfig):
    """`ReplayConfig` and the imagined steps of each controller update."""

    horizon: int = CONTROL.horizon


def imagine(variant: Variant, horizon: int, params, carry, action, frame, key, sample: bool):
    """`horizon` steps of the model fed its own predictions from `carry`, taking the pending
    `action` (for closed loop − the error input is then zero: `FinalProposal.imagine_step`).
    With `sample` the buttons executed are drawn from Bernoulli(ã) (their probability and draw
    are returned); without, ã itself is fed in. Returns per step `[H, N]`: rewards r̃, features
    h, the action probabilities and the executed buttons."""

    def body(c, k):
        carry, action, frame = c
        executed = draw_buttons(k, action) if sample else action
        carry, out = variant.imagine_step(params, carry, frame, executed)
        frame = jax.nn.sigmoid(out["logits"]) if "logits" in out else frame
        return (carry, out["action"], frame), {"reward": out["reward"], "h": variant.features(carry),
                                               "probs": action, "buttons": executed}

    _, traj = jax.lax.scan(body, (carry, action, frame), jax.random.split(key, horizon))
    return traj
