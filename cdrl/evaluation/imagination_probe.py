"""Does a world model's imagination tell which way to steer? Its imagined returns against the game's.

The privileged policy (a fifth of its steps random turns) plays `games` games (seeds 20000,
20001, ...: neither training nor held-out games) while the world model follows it teacher-forced
(`follow_step`). Every `every` steps, from that real state, the four button sequences of
`SEQUENCES` play `horizon` steps twice: in the game (from its state there, the same randomness
for every sequence) and in the model's imagination (`Variant.imagine_step` fed its own
predictions, as the `imagine`, `critic` and `value` controllers imagine). Real rewards count up
to the episode's end. The imagined reward is the variant's reward head's, else the look-ahead
reward head's (`cdrl.training.lookahead`).

`probe` reports, over the starts:

- `by_steps[k]`: imagined against real returns, both summed over the first k steps:
  `corr_all` (every start and sequence), `corr_steer` (the three steering sequences, each
  start's mean removed), `best_steer_agree` (where one steering sequence is the real best: the
  share where imagination ranks it first; a tie among n imagined firsts counts 1/n),
  `best_share_real` / `best_share_imagined`, `mean_real` / `mean_imagined` and the
  `accelerate_gap`s (straight on accelerating minus straight on);
- `by_horizon[H]`: the same ranking figures when imagination scores a sequence by its H-step
  imagined return plus γ^H V(h_H), the value head's value of the state it ends in (0 without a
  value head), against the real `horizon`-step return (a plain sum); `always_straight_agree`
  is the share of starts where straight on is the real best: the bar to beat;
- `reward_auc[k]`: how well the imagined reward at step k tells a real pellet (real reward
  > 0) from none, along straight on and along every sequence (`auc`);
- `value_corr`: the correlation of the value head's V(h_t) on the followed real states with the
  real discounted return from there (`discounted_returns`, γ the run's), None without a value
  head. The return is cut where the followed play stops: the game's end, or its last followed
  step, within 2 `every` steps of the episode's step limit;
- `value_corr_data` (`data_value_corr`): the same correlation on held-out episodes of the run's
  own data, whose policy the value was fitted to.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from cdrl.data.frames import as_float, model_obs
from cdrl.models.base import StepInput, Variant
from cdrl.training import lookahead

EXPLORE = 0.2  # the share of the privileged policy's steps replaced by random turns
GAME_SEED = 20000
SEQUENCES = {"straight": (0.0, 0.0, 0.0), "turn0": (1.0, 0.0, 0.0), "turn1": (0.0, 1.0, 0.0),
             "accelerate": (0.0, 0.0, 1.0)}
STEER = 3  # the first three sequences do not accelerate
HORIZON = 15  # the steps each sequence plays, and the real return sums over
HORIZONS = (1, 3, 5, 15)  # the imagined steps `by_horizon` ranks by
KS = (1, 5, 15)  # the steps `by_steps` sums over


# --------------------------------------------------------------------------- the followed play


def follow_step(variant: Variant, params, game, env_params, explore: float):
    """The body of a `jax.lax.scan` over the steps of one game, the privileged policy playing
    (a share `explore` of its steps random turns, `envs.policies.random_turns_instead`) and the
    model teacher-forced as a controller run acts: at step t it takes o_t and the buttons
    executed at o_t. Its carry is `start(...)`'s. Per step it gives h_t (the model's features
    after the step), the privileged buttons at o_t, whether the game was on at o_t, the model's
    input frame o_t `[H, W]` and the step's reward. After the step the carry holds the game at
    o_{t+1}, the model's state after (o_t, a_t) and its prediction õ_{t+1} (`[1, H, W]`; for a
    variant without a decoder, the last one given)."""
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
        obs, state, reward, term, trunc, _ = game.step(k_env, state, executed, env_params)
        nxt = (state, obs, carry, jnp.zeros((1,), bool), key, alive & ~(term | trunc), pred)
        return nxt, (variant.features(carry)[0], label, alive, frame[0], reward)

    return body


def start(variant: Variant, game, env_params, key):
    """The carry `follow_step`'s body starts a game from: the game reset by `key`'s first half,
    the model's initial state, the rest of the key for the steps."""
    k_reset, k_run = jax.random.split(key)
    obs, state = game.reset(k_reset, env_params)
    size = variant.arch.image_size
    return (state, obs, variant.init_carry(1), jnp.ones((1,), bool), k_run, jnp.array(True),
            jnp.zeros((1, size, size), jnp.float32))


def reward_source(variant: Variant, hp, choice: str | None = None) -> str:
    """Where the imagined reward comes from: `choice` ("lookahead" or "variant"), by default the
    look-ahead's reward head where the run trains one (it is fitted at every imagined step), else
    the variant's own. ValueError if the model has not that head, or imagines no actions."""
    if not variant.has_controller:
        raise ValueError(f"variant {variant.name!r} takes no actions, so it cannot imagine the steering choices "
                         "(a controller variant: action_loop, reward_prediction, final_proposal)")
    if choice not in (None, "lookahead", "variant"):
        raise ValueError(f"the imagined reward comes from 'lookahead' or 'variant', got {choice!r}")
    if choice == "variant" and not variant.predicts_reward:
        raise ValueError(f"variant {variant.name!r} has no reward head of its own (reward_prediction or "
                         "final_proposal have one)")
    if choice == "lookahead" and hp is None:
        raise ValueError("the run has no look-ahead reward head (train it with --lookahead-steps)")
    if choice is not None:
        return choice
    if hp is not None:
        return "lookahead"
    if variant.predicts_reward:
        return "variant"
    raise ValueError(f"variant {variant.name!r} has no reward head and the run no look-ahead heads "
                     "(train it with --lookahead-steps, or use reward_prediction or final_proposal)")


@functools.partial(jax.jit, static_argnames=("variant", "game", "points", "every", "horizon", "frames", "source"))
def _followed_branches(variant: Variant, params, game, env_params, hp, keys, *, points: int, every: int,
                       horizon: int, frames: bool, source: str):
    buttons = jnp.asarray(list(SEQUENCES.values()), jnp.float32)
    n = buttons.shape[0]
    heads = params.get("lookahead") if hp is not None else None

    def value(h):
        return lookahead.value(heads, h, hp) if heads is not None else jnp.zeros(h.shape[:-1])

    def value_after(h):  # what a branch's score adds after its rewards (`lookahead.value_after`)
        return lookahead.value_after(heads, h, hp) if heads is not None else jnp.zeros(h.shape[:-1])

    def real(key, state):
        def body(c, k):
            state, on = c
            obs, state, reward, term, trunc, _ = jax.vmap(game.step, (None, 0, 0, None))(k, state, buttons, env_params)
            shown = model_obs(obs, variant.arch) if frames else None
            return (state, on & ~(term | trunc)), (reward * on, on, shown)

        states = jax.tree.map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), state)
        return jax.lax.scan(body, (states, jnp.ones(n, bool)), jax.random.split(key, horizon))[1]

    def imagined(carry, frame):
        def body(c, _):
            carry, frame = c
            carry, out = variant.imagine_step(params, carry, frame, buttons)
            h = variant.features(carry)
            r = lookahead.reward(heads, h, hp) if source == "lookahead" else out["reward"]
            nxt = jax.nn.sigmoid(out["logits"]) if "logits" in out else frame
            shown = None
            if frames:
                shown = nxt if "logits" in out else jax.nn.sigmoid(variant.decode(params, out["pred_code"]))
            return (carry, nxt), (r.reshape(n), value_after(h), shown)

        carries = jax.tree.map(lambda x: jnp.repeat(x, n, axis=0), carry)
        return jax.lax.scan(body, (carries, jnp.repeat(frame, n, axis=0)), None, length=horizon)[1]

    follow = follow_step(variant, params, game, env_params, EXPLORE)

    def block(c, _):
        c, (h, _, alive, _, reward) = jax.lax.scan(follow, c, None, length=every)
        state, _, carry, _, key, on, pred = c
        r, r_on, r_frames = real(jax.random.fold_in(key, 1), state)
        i, v, i_frames = imagined(carry, pred)
        out = {"real": r, "on": r_on, "imagined": i, "value": v, "real_frames": r_frames, "imagined_frames": i_frames}
        return c, (out, on, value(h), reward * alive, alive)

    def one(key):
        return jax.lax.scan(block, start(variant, game, env_params, key), None, length=points)[1]

    return jax.vmap(one)(keys)


def followed_branches(variant: Variant, params, game, env_params, hp, *, games: int, points: int, every: int,
                      horizon: int, frames: bool = False, source: str | None = None) -> dict:
    """The followed play of `games` games and its branches at `points` starts, every `every`
    steps, as numpy arrays. Per game, start, sequence and step `[games, points, 4, horizon]`:
    `real` and `imagined` rewards, `on` (the game still on before the step), `value` (the
    return after the imagined step's reward, `lookahead.value_after`; 0 without a value head); with `frames`, `real_frames`
    and `imagined_frames` `[..., horizon, H, W]` in [0, 1]. Per start `[games, points]`: `alive`.
    Per followed step `[games, points * every]`: `followed_value` V(h_t), `followed_reward` and
    `followed_alive`. `source`: where the imagined rewards come from (`reward_source`)."""
    keys = jax.vmap(jax.random.PRNGKey)(GAME_SEED + jnp.arange(games))
    out, alive, v, reward, on = _followed_branches(variant, params, game, env_params, hp, keys, points=points,
                                                   every=every, horizon=horizon, frames=frames,
                                                   source=reward_source(variant, hp, source))
    # [games, points, horizon, sequences, ...] -> [games, points, sequences, horizon, ...]
    result = {name: np.moveaxis(np.asarray(x), 3, 2) for name, x in out.items() if x is not None}
    flat = lambda x: np.asarray(x).reshape(games, points * every)  # noqa: E731
    return {**result, "alive": np.asarray(alive), "followed_value": flat(v), "followed_reward": flat(reward),
            "followed_alive": flat(on)}


@functools.partial(jax.jit, static_argnames=("variant",))
def _episode_values(variant: Variant, params, hp, frames, actions):
    """V(h_t) after every step t of one recorded episode, fed teacher-forced: `[N - 1]`."""
    n = actions.shape[0]
    xs = StepInput(obs=frames[:, None], action=actions[:, None], is_first=(jnp.arange(n) == 0)[:, None])
    _, _, carries = variant.unroll_states(params, variant.init_carry(1), xs)
    return lookahead.value(params["lookahead"], variant.features(carries), hp)[:, 0]


def data_value_corr(variant: Variant, params, hp, episodes, gamma: float) -> tuple[float | None, int]:
    """The value head's V(h_t) after every step of `episodes` (recorded, fed teacher-forced)
    against the discounted return of the rewards that follow it, r_{t+1} on, cut at the
    episode's end: (their correlation over every step of every episode, the steps counted)."""
    eps = [episodes[i] for i in range(len(episodes)) if len(episodes[i].rewards) > 1]
    longest = max((len(ep.rewards) - 1 for ep in eps), default=0)
    values, returns = [], []
    for ep in eps:  # each padded to the longest: one compiled program; the unroll is causal
        n = len(ep.rewards) - 1
        pad = lambda x: np.concatenate([x[:n], np.zeros((longest - n,) + x.shape[1:], x.dtype)])  # noqa: E731
        v = _episode_values(variant, params, hp, as_float(jnp.asarray(pad(np.asarray(ep.frames)))),
                            jnp.asarray(pad(np.asarray(ep.actions, np.float32))))
        values.append(np.asarray(v)[:n])
        returns.append(discounted_returns(np.asarray(ep.rewards[1:], np.float64), gamma))
    if not values:
        return None, 0
    values, returns = np.concatenate(values), np.concatenate(returns)
    return corr(values, returns), int(values.size)


# --------------------------------------------------------------------------- the scores


def corr(a, b) -> float | None:
    """Pearson's correlation of two samples; None with fewer than two points or a constant one."""
    a, b = np.asarray(a, np.float64).ravel(), np.asarray(b, np.float64).ravel()
    if a.size < 2 or np.ptp(a) == 0 or np.ptp(b) == 0:
        return None
    return float(np.corrcoef(a, b)[0, 1])


def auc(scores, labels) -> float | None:
    """The area under the ROC curve of `scores` for the true `labels`: the chance that a random
    positive scores above a random negative, ties counted a half (the Mann-Whitney U over
    average ranks). None without positives or negatives."""
    scores, labels = np.asarray(scores, np.float64).ravel(), np.asarray(labels, bool).ravel()
    pos = int(labels.sum())
    neg = labels.size - pos
    if pos == 0 or neg == 0:
        return None
    _, inverse, counts = np.unique(scores, return_inverse=True, return_counts=True)
    ranks = (np.cumsum(counts) - (counts - 1) / 2.0)[inverse]  # 1-based, ties at their mean rank
    return float((ranks[labels].sum() - pos * (pos + 1) / 2.0) / (pos * neg))


def discounted_returns(rewards: np.ndarray, gamma: float) -> np.ndarray:
    """G_t = r_t + γ G_{t+1} along the last axis, G = 0 after its end (the return truncated there)."""
    out = np.zeros(np.shape(rewards), np.float64)
    nxt = np.zeros(np.shape(rewards)[:-1], np.float64)
    for t in range(np.shape(rewards)[-1] - 1, -1, -1):
        nxt = rewards[..., t] + gamma * nxt
        out[..., t] = nxt
    return out


def rank_scores(real: np.ndarray, imagined: np.ndarray) -> dict:
    """The ranking figures of per-start returns `[starts, sequences]`: over the starts whose
    steering sequences have one real best, how often imagination ranks it first (a tie among n
    imagined firsts counts 1/n), which sequence each names, and the correlations."""
    rs, is_ = real[:, :STEER], imagined[:, :STEER]
    unique = (rs == rs.max(1, keepdims=True)).sum(1) == 1
    n = int(unique.sum())
    best_r = np.argmax(rs[unique], 1)
    first = is_[unique] == is_[unique].max(1, keepdims=True)
    credit = first / first.sum(1, keepdims=True)  # each start's one vote, split over its imagined firsts
    dr, di = rs - rs.mean(1, keepdims=True), is_ - is_.mean(1, keepdims=True)
    return {
        "corr_all": corr(real, imagined),
        "corr_steer": corr(dr[unique], di[unique]) if n else None,
        "best_steer_agree": float(credit[np.arange(n), best_r].mean()) if n else None,
        "always_straight_agree": float(np.mean(best_r == 0)) if n else None,
        "starts_with_one_best": n,
        "best_share_real": (np.bincount(best_r, minlength=STEER) / max(1, n)).tolist(),
        "best_share_imagined": (credit.sum(0) / max(1, n)).tolist(),
    }


def scores(real: np.ndarray, imagined: np.ndarray, ks) -> dict:
    """`by_steps` from `[starts, sequences, horizon]` rewards: per k, the returns of the first k steps."""
    out = {}
    for k in ks:
        r, i = real[..., :k].sum(-1), imagined[..., :k].sum(-1)
        out[str(k)] = {**rank_scores(r, i), "mean_real": r.mean(0).tolist(), "mean_imagined": i.mean(0).tolist(),
                       "accelerate_gap_real": float(np.mean(r[:, 3] - r[:, 0])),
                       "accelerate_gap_imagined": float(np.mean(i[:, 3] - i[:, 0]))}
    return out


def horizon_scores(real: np.ndarray, imagined: np.ndarray, values: np.ndarray, gamma: float, horizons) -> dict:
    """`by_horizon` from `[starts, sequences, horizon]` rewards and values: imagination scores a
    sequence by its first H imagined rewards plus γ^H times the value after step H, against the
    real return over every step."""
    r = real.sum(-1)
    return {str(h): rank_scores(r, imagined[..., :h].sum(-1) + gamma ** h * values[..., h - 1]) for h in horizons}


def reward_aucs(real: np.ndarray, imagined: np.ndarray, on: np.ndarray) -> dict:
    """Per imagined step k (1 .. horizon), the `auc` of the imagined reward for a real pellet
    (real reward > 0) at that step, where the game was still on: along straight on, and along
    every sequence."""
    steps = real.shape[-1]
    pick = {"straight": slice(0, 1), "all": slice(None)}
    return {name: [auc(imagined[:, s, k][on[:, s, k]], real[:, s, k][on[:, s, k]] > 0) for k in range(steps)]
            for name, s in pick.items()}


def probe(variant: Variant, params, game, env_params, hp, gamma: float, *, max_steps: int, games: int = 32,
          every: int = 10, horizon: int = HORIZON, ks=KS, reward_from: str | None = None) -> dict:
    """The module's figures for a world model (`params`, with `params["lookahead"]` when `hp` is
    not None) on `game`, starts every `every` steps up to `max_steps`; the imagined rewards from
    `reward_from` (`reward_source`)."""
    source = reward_source(variant, hp, reward_from)
    if games < 1 or every < 1 or max_steps // every < 2:
        raise ValueError(f"{games} games with a start every {every} steps of {max_steps} leave no start")
    points = max_steps // every - 1
    b = followed_branches(variant, params, game, env_params, hp, games=games, points=points, every=every,
                          horizon=horizon, source=source)
    alive = b["alive"]
    real, imagined, values, on = (b[name][alive] for name in ("real", "imagined", "value", "on"))
    followed = b["followed_alive"]
    returns = discounted_returns(b["followed_reward"], gamma)
    has_value = hp is not None
    return {
        "starts": int(alive.sum()),
        "reward_source": source,
        "by_steps": scores(real, imagined, [k for k in ks if k <= horizon]),
        "by_horizon": horizon_scores(real, imagined, values, gamma, [h for h in HORIZONS if h <= horizon]),
        "reward_auc": reward_aucs(real, imagined, on),
        "value_head": has_value,
        "value_corr": corr(b["followed_value"][followed], returns[followed]) if has_value else None,
        "value_states": int(followed.sum()),
    }
