"""Losses over a few imagined steps, and the heads that read the model's state.

One-step, teacher-forced training teaches a model to predict the next frame from a real one.
Imagination feeds it its own predictions, which it never saw in training. These losses train
that path, as TD-MPC2 and MuZero train their latent dynamics over a few unrolled steps:

1. the chunk is unrolled teacher-forced, as `chunk_loss` does, keeping the carry of every step;
2. from every `stride`-th step s, the model imagines `steps` K more steps
   (`Variant.imagine_step`: fed its own predicted frame, or a zero error for closed loop −),
   taking the recorded buttons a_{s+1} .. a_{s+K};
3. imagined step k is scored against the real o_{s+k+1} and r_{s+k+1} (frame BCE, the
   variant's reward MSE and its error balanced over the reward's sign classes), while it stays
   inside the chunk and its episode.

Three heads read the model's state h (`Variant.features`) at every real step and every
imagined one. They live in `params["lookahead"]`:

- `reward`: r_{t+1} as a two-hot distribution over symlog-spaced bins (DreamerV3);
- `cont`: the logit that the episode goes on after the step;
- `value`: the λ-return from the state, two-hot as the reward. Its targets are real
  λ-returns of the chunk's rewards, bootstrapped by a slow copy of the head (`value_target`,
  an exponential moving average of `value`, `update_target`). The state h_t has seen a_t, so
  the value is the return of a_t's own reward r_{t+1} and the rest: an action value. With
  `backup` "max" each step bootstraps on the best of the eight buttons pressed with the next
  real frame (Peng's Q(λ)), the value of acting greedily on it rather than the data's.

With `frame_value` a fourth head reads frames, not h: `frame_value`, a small CNN of the
encoder's shape and an MLP. It learns the return from s_{t+1} on from the model's predicted
frame õ_{t+1} (0 after the episode's end), so a plan's predicted last frame can be valued
(`mpc_planner`). A value of the state after a plan then reads the layout the plan leads to.

With `advantage` a fifth head A(h_t) learns the λ-return less the mean of the slow value
head's values of the eight buttons at the same state (`branch_values`): the buttons' contrast
without the state's level (Baird's advantage learning; Wang et al. 2016's dueling heads).

The heads' gradient into the model is scaled by `head_grad` (`scale_grad`): at full scale a
reward loss's gradient into the core is hundreds of times the frame BCE's, which holds the
frames at their mean.
"""
from __future__ import annotations

import flax.struct
import jax
import jax.numpy as jnp

from cdrl.models import nets
from cdrl.models.base import BUTTON_COMBOS, StepInput, Variant, elementwise_bce
from cdrl.models.controller import balanced_squared_error
from cdrl.training.optim import OptHParams
from cdrl.training.twohot import expected, two_hot_loss

# The value's targets: the data's own λ-returns, or Peng's Q(λ) over the eight buttons.
VALUE_BACKUPS = ("lambda", "max")
# The names of the look-ahead loss terms (each with a weight of the same name in `HParams`).
TERMS = ("imag_obs_bce", "imag_reward_mse", "imag_reward_balanced", "reward_twohot", "cont_bce", "value_twohot",
         "frame_value_twohot", "advantage_mse")
# Their metrics beside them (weight 0): the heads' expected values against their targets.
METRICS = ("reward_head_mse", "value_mse")
DEFAULT_WEIGHTS = {"imag_obs_bce": 1.0, "imag_reward_mse": 1.0, "imag_reward_balanced": 0.0, "reward_twohot": 1.0,
                   "cont_bce": 1.0, "value_twohot": 1.0, "frame_value_twohot": 1.0, "advantage_mse": 1.0,
                   "reward_head_mse": 0.0,
                   "value_mse": 0.0}


@flax.struct.dataclass
class LookaheadHParams:
    """The look-ahead's numbers. Static: `steps` K imagined from every `stride`-th real step,
    the heads' `bins` over symlog values in [-`limit`, `limit`] and their `hidden` width.
    Static too: the value's `backup` (`VALUE_BACKUPS`), whether a `frame_value` head values
    predicted frames and whether an `advantage` head contrasts the buttons of one state.
    Traced: the heads' own optimiser `head_opt`, the discount `gamma` and `lam` of the value's
    λ-returns, the target head's EMA `target_decay`, and `head_grad`, the scale of the heads'
    gradient into the model. The terms' weights are `HParams.loss_weights`'s (`default_weights`)."""

    head_opt: OptHParams
    gamma: jax.Array
    lam: jax.Array
    target_decay: jax.Array
    head_grad: jax.Array
    steps: int = flax.struct.field(pytree_node=False, default=3)
    stride: int = flax.struct.field(pytree_node=False, default=3)
    bins: int = flax.struct.field(pytree_node=False, default=41)
    limit: float = flax.struct.field(pytree_node=False, default=4.0)
    hidden: int = flax.struct.field(pytree_node=False, default=64)
    backup: str = flax.struct.field(pytree_node=False, default="lambda")
    frame_value: bool = flax.struct.field(pytree_node=False, default=False)
    advantage: bool = flax.struct.field(pytree_node=False, default=False)

    @classmethod
    def create(cls, steps: int = 3, stride: int | None = None, head_opt: OptHParams | None = None,
               gamma: float = 0.99, lam: float = 0.95, target_decay: float = 0.98, head_grad: float = 0.01,
               bins: int = 41, limit: float = 4.0, hidden: int = 64, backup: str = "lambda",
               frame_value: bool = False, advantage: bool = False) -> "LookaheadHParams":
        """`stride` defaults to `steps`: K imagined steps from every K-th real step cost about
        one more pass over the chunk. `head_opt` defaults to Adam at 3e-4, the gradient's norm
        clipped at 100."""
        stride = steps if stride is None else stride
        if steps < 1 or stride < 1:
            raise ValueError(f"look-ahead steps and stride must be >= 1, got {steps} and {stride}")
        if bins < 2 or limit <= 0:
            raise ValueError(f"two-hot needs bins >= 2 and limit > 0, got {bins} and {limit}")
        if backup not in VALUE_BACKUPS:
            raise ValueError(f"the value's backup must be one of {', '.join(VALUE_BACKUPS)}; got {backup!r}")
        f32 = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
        head_opt = head_opt if head_opt is not None else OptHParams.create("adam", lr=3e-4, grad_clip=100.0)
        return cls(head_opt, f32(gamma), f32(lam), f32(target_decay), f32(head_grad), steps=steps, stride=stride,
                   bins=bins, limit=limit, hidden=hidden, backup=backup, frame_value=frame_value,
                   advantage=advantage)

    @staticmethod
    def default_weights() -> dict[str, float]:
        """The weight of every look-ahead term, by name (`TERMS`, then the `METRICS` at 0)."""
        return dict(DEFAULT_WEIGHTS)

    @property
    def bin_values(self) -> jax.Array:
        """The bins' centres in symlog space, evenly spaced from -limit to limit."""
        return jnp.linspace(-self.limit, self.limit, self.bins)


# --------------------------------------------------------------------------- the heads


def init_heads(key: jax.Array, arch, hp: LookaheadHParams) -> dict:
    """The reward, continuation and value heads (MLPs of one hidden layer on h, of `arch`'s
    `lstm_size`) and the value's target copy; with `hp.frame_value`, the frame value (a CNN of
    `arch`'s encoder shape, then an MLP). The two-hot heads' last layers start at zero: they
    predict 0 at first."""
    k_reward, k_cont, k_value = jax.random.split(key, 3)
    features = arch.lstm_size

    def head(k, out, zero_last):
        p = nets.init_mlp(k, (features, hp.hidden, out), final_selu=False)
        if zero_last:
            p["dense1"] = jax.tree.map(jnp.zeros_like, p["dense1"])
        return p

    value = head(k_value, hp.bins, True)
    heads = {"reward": head(k_reward, hp.bins, True), "cont": head(k_cont, 1, False), "value": value,
             "value_target": jax.tree.map(jnp.copy, value)}
    if hp.frame_value:
        k_enc, k_mlp = jax.random.split(jax.random.fold_in(key, 1))
        mlp = nets.init_mlp(k_mlp, (arch.obs_code, hp.hidden, hp.bins), final_selu=False)
        heads["frame_value"] = {"enc": nets.init_obs_encoder(k_enc, arch),
                                "mlp": {**mlp, "dense1": jax.tree.map(jnp.zeros_like, mlp["dense1"])}}
    if hp.advantage:
        heads["advantage"] = head(jax.random.fold_in(key, 2), 1, True)
    return heads


def with_heads(variant: Variant, params: dict, key: jax.Array, hp: LookaheadHParams | None) -> dict:
    """`params` with the look-ahead heads added (unchanged when `hp` is None)."""
    if hp is None:
        return params
    if not variant.has_controller:
        raise ValueError(f"the look-ahead losses imagine through a model's own actions; variant {variant.name!r} "
                         "has none (action_loop, reward_prediction or final_proposal)")
    return {**params, "lookahead": init_heads(jax.random.fold_in(key, 7), variant.arch, hp)}


def scale_grad(x: jax.Array, scale: jax.Array) -> jax.Array:
    """x, its gradient multiplied by `scale` on the way back."""
    return scale * x + jax.lax.stop_gradient((1.0 - scale) * x)


def value(heads: dict, h: jax.Array, hp: LookaheadHParams, target: bool = False) -> jax.Array:
    """The value head's expected λ-return from states h `[..., F]` (`target`: the slow copy's)."""
    return expected(nets.mlp(heads["value_target" if target else "value"], h, final_selu=False), hp.bin_values)


def reward(heads: dict, h: jax.Array, hp: LookaheadHParams) -> jax.Array:
    """The reward head's expected r_{t+1} from states h."""
    return expected(nets.mlp(heads["reward"], h, final_selu=False), hp.bin_values)


def value_after(heads: dict, h: jax.Array, hp: LookaheadHParams) -> jax.Array:
    """The return after the reward of the step h has taken: (V(h) − r(h)) / γ. The state h_t has
    seen a_t, and the value's targets hold a_t's own reward r_{t+1}; a return that has already
    counted r(h) adds γ times this, not V(h)."""
    return (value(heads, h, hp) - reward(heads, h, hp)) / hp.gamma


def advantage(heads: dict, h: jax.Array) -> jax.Array:
    """The advantage head's A(h): the return of the buttons h has taken less the mean over the
    eight of the state before them."""
    return nets.mlp(heads["advantage"], h, final_selu=False)[..., 0]


def frame_value_logits(heads: dict, frames: jax.Array, arch, hp: LookaheadHParams) -> jax.Array:
    """The frame value's two-hot logits for frames `[N, H, W]` in [0, 1] (`arch`: the model's)."""
    code = nets.obs_encoder(heads["frame_value"]["enc"], arch, frames)
    return nets.mlp(heads["frame_value"]["mlp"], code, final_selu=False)


def frame_value(heads: dict, frames: jax.Array, arch, hp: LookaheadHParams) -> jax.Array:
    """The frame value's expected return from the states that frames `[..., H, W]` show."""
    lead = frames.shape[:-2]
    flat = frames.reshape((-1,) + frames.shape[-2:])
    return expected(frame_value_logits(heads, flat, arch, hp), hp.bin_values).reshape(lead)


def update_target(params: dict, hp: LookaheadHParams | None) -> dict:
    """`params` with the value's target copy moved towards the value head:
    target <- decay target + (1 - decay) value."""
    if hp is None:
        return params
    heads = params["lookahead"]
    target = jax.tree.map(lambda t, v: hp.target_decay * t + (1.0 - hp.target_decay) * v, heads["value_target"],
                          heads["value"])
    return {**params, "lookahead": {**heads, "value_target": target}}


def head_mask(params: dict) -> dict:
    """1 on the look-ahead heads' parameters, 0 elsewhere (a pytree like `params`)."""
    return {k: jax.tree.map(jnp.ones_like if k == "lookahead" else jnp.zeros_like, v) for k, v in params.items()}


# --------------------------------------------------------------------------- returns and masks


def lambda_returns(rewards, values, last, gamma, lam, not_done=None):
    """R_k = r_k + γ d_k ((1 - λ_k) V_{k+1} + λ_k R_{k+1}), R_H = `last`: λ-returns of `[H, N]`
    rewards with the values V_1 .. V_H after each step; `not_done` d_k (default 1) is 0 where the
    episode ended with r_k, which then bootstraps nothing; `lam` a number or one per step."""
    not_done = jnp.ones_like(rewards) if not_done is None else jnp.broadcast_to(not_done, rewards.shape)
    lam = jnp.broadcast_to(lam, rewards.shape)

    def body(nxt, x):
        r, v_next, nd, lam_k = x
        ret = r + gamma * nd * ((1.0 - lam_k) * v_next + lam_k * nxt)
        return ret, ret

    _, rets = jax.lax.scan(body, last, (rewards, values, not_done, lam), reverse=True)
    return rets


def targets(is_first: jax.Array, rewards: jax.Array, target_values: jax.Array, hp: LookaheadHParams,
            truncated: jax.Array | None = None, next_best: jax.Array | None = None):
    """Per real step t of a chunk `[T, B]`: whether the episode goes on after it (`cont`, known
    for t < T - 1), and the λ-return from its state (`ret`, known for t < T - 1: the last step's
    is the bootstrap), with `known` masks for both. `target_values` are the slow head's values
    after every step. An episode that a step limit cut (`truncated`, `Chunk.truncated`) goes on
    in the game: its last step bootstraps on its own state's value, r_{t+1} + γ V(h_t), as the
    next state's is not in the chunk (Pardo et al. 2018, time limits in RL). `next_best`
    `[T - 1, B]` (backup "max", `best_values`): the best button's value at each next step, which
    then bootstraps in place of the data's own, V(h_{t+1})."""
    ended = is_first[1:]  # o_{t+1} starts a new episode: step t ended one
    cut = ended & truncated[:-1] if truncated is not None else jnp.zeros_like(ended)
    terminal = (ended & ~cut).astype(jnp.float32)
    cont = jnp.concatenate([1.0 - terminal, jnp.ones_like(terminal[:1])])
    v_next = jnp.where(cut, target_values[:-1], target_values[1:] if next_best is None else next_best)
    ret = lambda_returns(rewards[:-1], v_next, target_values[-1], hp.gamma, jnp.where(cut, 0.0, hp.lam),
                         1.0 - terminal)
    ret = jnp.concatenate([ret, target_values[-1:]])
    known = jnp.arange(is_first.shape[0])[:, None] < is_first.shape[0] - 1
    return cont, ret, jnp.broadcast_to(known, is_first.shape)


def branch_values(variant: Variant, params, hp: LookaheadHParams, carries, xs: StepInput) -> jax.Array:
    """`[8, T - 1, B]`: for each real step t ≥ 1 of a chunk, the slow value head's value of each
    of the eight button combinations pressed with o_t from the carry before it (`carries[t - 1]`),
    as `mpc_planner` scores one-step plans. Peng's Q(λ) bootstraps on their best (backup "max");
    the advantage's baseline is their mean."""
    prev = jax.tree.map(lambda x: x[:-1].reshape((-1,) + x.shape[2:]), carries)
    obs, first = xs.obs[1:], xs.is_first[1:]
    n = first.size

    def of(buttons):
        x = StepInput(obs=obs.reshape((n,) + obs.shape[2:]), action=jnp.broadcast_to(buttons, (n,) + buttons.shape),
                      is_first=first.reshape(n))
        carry, _ = variant.step(params, prev, x)
        return value(params["lookahead"], variant.features(carry), hp, target=True)

    return jax.vmap(of)(jnp.asarray(BUTTON_COMBOS)).reshape((-1,) + first.shape)


def imagined_index(num_steps: int, hp: LookaheadHParams):
    """The imagined steps' real indices: `starts` [S] (every `stride`-th step) and `index`
    [S, K], the real step s + k that imagined step k from start s stands for (clipped to the
    chunk; `inside` [S, K] says where it is not)."""
    starts = jnp.arange(0, num_steps, hp.stride)
    index = starts[:, None] + jnp.arange(1, hp.steps + 1)[None, :]
    return starts, jnp.minimum(index, num_steps - 1), index < num_steps


def same_episode(is_first: jax.Array, starts: jax.Array, hp: LookaheadHParams) -> jax.Array:
    """[S, K, B]: no episode starts between real step s and s + k (both included after s)."""
    padded = jnp.concatenate([is_first, jnp.ones((hp.steps,) + is_first.shape[1:], bool)])
    window = jax.vmap(lambda s: jax.lax.dynamic_slice_in_dim(padded, s + 1, hp.steps))(starts)  # [S, K, B]
    return jnp.cumsum(window.astype(jnp.int32), axis=1) == 0


# --------------------------------------------------------------------------- the losses


def _mean(x: jax.Array, mask: jax.Array) -> jax.Array:
    mask = jnp.broadcast_to(mask, x.shape).astype(jnp.float32)
    return jnp.sum(x * mask) / jnp.maximum(jnp.sum(mask), 1.0)


def imagine_from(variant: Variant, params, carries, frames, actions):
    """K imagined steps from each start: `carries` `[S, B, ...]`, the first fed frame `frames`
    `[S, B, H, W]` (the real step's prediction) and the buttons `actions` `[S, K, B, A]`. Returns
    per step `[S, K, B, ...]`: frame logits, the variant's reward r̃ (0 when it has none) and h."""

    def one(carry, frame, acts):
        def body(c, a):
            carry, frame = c
            carry, out = variant.imagine_step(params, carry, frame, a)
            logits = out["logits"] if "logits" in out else variant.decode(params, out["pred_code"])
            r = out["reward"] if "reward" in out else jnp.zeros(a.shape[:1])
            return (carry, jax.nn.sigmoid(logits)), (logits, r, variant.features(carry))

        return jax.lax.scan(body, (carry, frame), acts)[1]

    return jax.vmap(one)(carries, frames, actions)


def lookahead_terms(variant: Variant, params, hp: LookaheadHParams, xs: StepInput, outs, carries,
                    next_obs: jax.Array, rewards: jax.Array, truncated: jax.Array | None = None) -> dict:
    """The look-ahead's terms (`TERMS` and `METRICS`) of one chunk, from its teacher-forced
    outputs `outs` and the carry after every step `carries` (`[T, B, ...]`); `truncated`:
    `Chunk.truncated`."""
    heads = params["lookahead"]
    bins = hp.bin_values
    steps_t = xs.is_first.shape[0]
    starts, index, inside = imagined_index(steps_t, hp)
    valid = inside[:, :, None] & same_episode(xs.is_first, starts, hp)  # [S, K, B]

    pick = lambda tree, i: jax.tree.map(lambda x: x[i], tree)  # noqa: E731
    logits, imag_r, imag_h = imagine_from(variant, params, pick(carries, starts),
                                          jax.nn.sigmoid(outs["logits"][starts]), xs.action[index])
    pixel = jnp.mean(elementwise_bce(logits, next_obs[index]), axis=(-2, -1))
    terms = {"imag_obs_bce": _mean(pixel, valid),
             "imag_reward_mse": _mean(jnp.square(imag_r - rewards[index]), valid),
             "imag_reward_balanced": balanced_squared_error(imag_r, rewards[index], mask=valid)}

    real_h = variant.features(carries)  # [T, B, F]
    fixed = jax.lax.stop_gradient(params)
    branches = branch_values(variant, fixed, hp, jax.lax.stop_gradient(carries), xs) \
        if hp.backup == "max" or hp.advantage else None
    next_best = jnp.max(branches, axis=0) if hp.backup == "max" else None
    cont, ret, known = targets(xs.is_first, rewards, value(heads, jax.lax.stop_gradient(real_h), hp, target=True), hp,
                               truncated, next_best)
    ret = jax.lax.stop_gradient(ret)
    # The heads see the real steps [T, B] and the imagined ones [S * K, B], side by side.
    h = scale_grad(jnp.concatenate([real_h, imag_h.reshape((-1,) + imag_h.shape[2:])]), hp.head_grad)
    flat = lambda x: jnp.concatenate([x, x[index].reshape((-1,) + x.shape[1:])])  # noqa: E731
    mask = jnp.concatenate([jnp.ones_like(xs.is_first), valid.reshape((-1,) + valid.shape[2:])])
    r_logits = nets.mlp(heads["reward"], h, final_selu=False)
    c_logits = nets.mlp(heads["cont"], h, final_selu=False)[..., 0]
    v_logits = nets.mlp(heads["value"], h, final_selu=False)
    r_target, c_target, v_target, v_known = flat(rewards), flat(cont), flat(ret), flat(known)
    terms["reward_twohot"] = _mean(two_hot_loss(r_logits, r_target, bins), mask)
    terms["cont_bce"] = _mean(elementwise_bce(c_logits, c_target), mask & v_known)
    terms["value_twohot"] = _mean(two_hot_loss(v_logits, v_target, bins), mask & v_known)
    terms["reward_head_mse"] = _mean(jnp.square(expected(r_logits, bins) - r_target), mask)
    terms["value_mse"] = _mean(jnp.square(expected(v_logits, bins) - v_target), mask & v_known)
    terms["frame_value_twohot"] = frame_value_term(variant, heads, hp, outs, ret, known, xs.is_first, truncated) \
        if hp.frame_value else jnp.zeros(())
    if hp.advantage:
        # A(h_t) against the λ-return less the mean of the eight buttons' values at the same state
        a = nets.mlp(heads["advantage"], h[1:steps_t], final_selu=False)[..., 0]
        terms["advantage_mse"] = _mean(jnp.square(a - (ret[1:] - jnp.mean(branches, axis=0))),
                                       known[1:] & ~xs.is_first[1:])
    else:
        terms["advantage_mse"] = jnp.zeros(())
    return terms


def frame_value_term(variant: Variant, heads, hp: LookaheadHParams, outs, ret, known, is_first, truncated):
    """The frame value's two-hot cross-entropy on a chunk: from the predicted frame õ_{t+1} of
    each real step t, the λ-return from step t + 1 on (`ret[t + 1]`), or 0 where step t ended
    its episode (not where a step limit cut it: that return is unknown)."""
    t = is_first.shape[0]
    frames = scale_grad(jax.nn.sigmoid(outs["logits"][:-1]), hp.head_grad)  # õ_1 .. õ_{T-1}
    ended = is_first[1:]
    cut = ended & truncated[:-1] if truncated is not None else jnp.zeros_like(ended)
    target = jnp.where(ended, 0.0, ret[1:])
    mask = (ended & ~cut) | (known[1:] & ~ended)
    logits = frame_value_logits(heads, frames.reshape((-1,) + frames.shape[2:]), variant.arch, hp)
    loss = two_hot_loss(logits.reshape((t - 1,) + ended.shape[1:] + (hp.bins,)), target, hp.bin_values)
    return _mean(loss, mask)

