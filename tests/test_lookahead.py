"""The look-ahead losses (`cdrl.training.lookahead`) against plain written-out loops: two-hot
codes (`cdrl.training.twohot`), and every term of a chunk computed start by start and step by
step in Python; the heads' own optimiser and the target copy."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdrl.data.stream import Chunk
from cdrl.models import TINY, StepInput, make_variant, nets
from cdrl.models.base import BUTTON_COMBOS
from cdrl.runs.config import RunConfig
from cdrl.training import lookahead as la
from cdrl.training import twohot as th
from cdrl.training.optim import HParams
from cdrl.training.step import chunk_loss, init_state, train_step

T, B = 7, 2


def _chunk(seed=0, truncated=False):
    k = jax.random.split(jax.random.PRNGKey(seed), 4)
    frames = jax.random.uniform(k[0], (T + 1, B, TINY.image_size, TINY.image_size))
    is_first = np.zeros((T, B), bool)
    is_first[0] = True
    is_first[4, 1] = True  # stream 1 starts a new episode at step 4
    return Chunk(obs=frames[:-1], next_obs=frames[1:],
                 action=(jax.random.uniform(k[1], (T, B, 3)) > 0.5).astype(jnp.float32),
                 reward=jnp.round(jax.random.normal(k[2], (T, B)), 1) * (jax.random.uniform(k[3], (T, B)) > 0.4),
                 is_first=jnp.asarray(is_first),
                 truncated=jnp.asarray(np.roll(is_first, -1, axis=0) & truncated) if truncated else None)


def test_two_hot_puts_its_mass_on_the_two_nearest_bins_and_keeps_the_mean():
    bins = jnp.linspace(-2.0, 2.0, 5)  # -2 -1 0 1 2
    code = np.asarray(th.two_hot(jnp.asarray([0.25, -1.0, 7.0, -9.0]), bins))
    np.testing.assert_allclose(code[0], [0, 0, 0.75, 0.25, 0], atol=1e-6)
    np.testing.assert_allclose(code[1], [0, 1, 0, 0, 0], atol=1e-6)
    np.testing.assert_allclose(code[2], [0, 0, 0, 0, 1], atol=1e-6)  # clipped to the ends
    np.testing.assert_allclose(code[3], [1, 0, 0, 0, 0], atol=1e-6)
    y = jnp.linspace(-1.9, 1.9, 17)
    np.testing.assert_allclose(th.two_hot(y, bins) @ bins, y, atol=1e-5)


def test_a_head_that_puts_its_logits_on_the_two_hot_code_predicts_the_value():
    bins = la.LookaheadHParams.create().bin_values
    x = jnp.asarray([-3.0, -0.5, 0.0, 0.5, 12.0])
    logits = jnp.log(th.two_hot(th.symlog(x), bins) + 1e-12)
    np.testing.assert_allclose(th.expected(logits, bins), x, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(th.symexp(th.symlog(x)), x, rtol=1e-6)


def _by_hand(variant, params, hp, chunk, weights):
    """Every look-ahead term of `chunk`, start by start, step by step, with Python loops."""
    heads = params["lookahead"]
    bins = np.asarray(hp.bin_values)
    mlp = lambda p, h: np.asarray(jnp.asarray(  # noqa: E731
        jax.nn.selu(h @ p["dense0"]["kernel"] + p["dense0"]["bias"]) @ p["dense1"]["kernel"] + p["dense1"]["bias"]))

    def softmax(z):
        e = np.exp(z - z.max())
        return e / e.sum()

    def twohot_ce(z, y):
        s = np.sign(y) * np.log1p(abs(y))
        s = min(max(s, bins[0]), bins[-1])
        i = min(int(np.searchsorted(bins, s, side="right")) - 1, len(bins) - 2)
        w = (s - bins[i]) / (bins[i + 1] - bins[i])
        logp = np.log(softmax(z))
        return -((1 - w) * logp[i] + w * logp[i + 1])

    def decode(z):
        m = softmax(z) @ bins
        return np.sign(m) * np.expm1(abs(m))

    obs = np.asarray(chunk.obs)
    nxt = np.asarray(chunk.next_obs)
    act, rew, first = np.asarray(chunk.action), np.asarray(chunk.reward), np.asarray(chunk.is_first)
    cut = np.zeros_like(first) if chunk.truncated is None else np.asarray(chunk.truncated)
    carry, carries, preds = variant.init_carry(B), [], []
    for t in range(T):
        carry, out = variant.step(params, carry, StepInput(obs=jnp.asarray(obs[t]), action=jnp.asarray(act[t]),
                                                           is_first=jnp.asarray(first[t])))
        carries.append(carry)
        preds.append(jax.nn.sigmoid(out["logits"]))
    real_h = np.stack([np.asarray(variant.features(c)) for c in carries])  # [T, B, F]
    target_v = np.stack([[decode(mlp(heads["value_target"], real_h[t, b])) for b in range(B)] for t in range(T)])
    # each of the eight buttons pressed with o_t from the carry before it: the slow value there
    branch = np.zeros((len(BUTTON_COMBOS), T, B))
    for t in range(1, T) if hp.backup == "max" or hp.advantage else ():
        for i, combo in enumerate(BUTTON_COMBOS):
            c, _ = variant.step(params, carries[t - 1], StepInput(
                obs=jnp.asarray(obs[t]), action=jnp.tile(jnp.asarray(combo), (B, 1)), is_first=jnp.asarray(first[t])))
            h = np.asarray(variant.features(c))
            branch[i, t] = [decode(mlp(heads["value_target"], h[b])) for b in range(B)]
    # what V_{t+1} bootstraps on: the data's own buttons, or the best of the eight
    boot = branch.max(axis=0) if hp.backup == "max" else target_v
    ret = np.zeros((T, B))
    for b in range(B):
        ret[T - 1, b] = target_v[T - 1, b]
        for t in reversed(range(T - 1)):
            if cut[t, b]:  # the step limit ended the episode: the state's own value stands for the next one's
                ret[t, b] = rew[t, b] + hp.gamma * target_v[t, b]
                continue
            goes_on = 0.0 if first[t + 1, b] else 1.0
            ret[t, b] = rew[t, b] + hp.gamma * goes_on * ((1 - hp.lam) * boot[t + 1, b] + hp.lam * ret[t + 1, b])
    # (h, reward target, continuation target or None, return target or None) of every scored state
    scored = [(real_h[t, b], rew[t, b], None if t == T - 1 else float(not first[t + 1, b] or cut[t, b]),
               None if t == T - 1 else ret[t, b]) for t in range(T) for b in range(B)]
    imag_bce, imag_mse, imag_sign = [], [], []
    for s in range(0, T, hp.stride):
        for b in range(B):
            c = jax.tree.map(lambda x: x[b:b + 1], carries[s])
            frame = preds[s][b:b + 1]
            for k in range(1, hp.steps + 1):
                i = s + k
                if i >= T or first[s + 1:i + 1, b].any():
                    break
                c, out = variant.imagine_step(params, c, frame, jnp.asarray(act[i, b][None]))
                logits = out["logits"] if "logits" in out else variant.decode(params, out["pred_code"])
                frame = jax.nn.sigmoid(logits)
                lg, target = np.asarray(logits[0], np.float64), nxt[i, b]
                imag_bce.append(np.mean(np.logaddexp(0, lg) - target * lg))
                imag_mse.append((float(out["reward"][0]) - rew[i, b]) ** 2)
                imag_sign.append(np.sign(rew[i, b]) if abs(rew[i, b]) > 1e-6 else 0.0)
                h = np.asarray(variant.features(c))[0]
                scored.append((h, rew[i, b], None if i == T - 1 else float(not first[i + 1, b] or cut[i, b]),
                               None if i == T - 1 else ret[i, b]))
    r_ce, c_bce, v_ce, r_mse, v_mse = [], [], [], [], []
    for h, r, cont, ret_t in scored:
        zr, zc, zv = mlp(heads["reward"], h), mlp(heads["cont"], h)[0], mlp(heads["value"], h)
        r_ce.append(twohot_ce(zr, r))
        r_mse.append((decode(zr) - r) ** 2)
        if cont is not None:
            c_bce.append(np.logaddexp(0, zc) - cont * zc)
            v_ce.append(twohot_ce(zv, ret_t))
            v_mse.append((decode(zv) - ret_t) ** 2)
    # the advantage: on the real steps t >= 1 with a known return, that return less the eight buttons' mean value
    adv = [(mlp(heads["advantage"], real_h[t, b])[0] - (ret[t, b] - branch[:, t, b].mean())) ** 2
           for t in range(1, T - 1) for b in range(B) if hp.advantage and not first[t, b]]
    # the frame value: from the predicted frame of step t, the return from t + 1 on (0 after an episode's end)
    f_ce = []
    if hp.frame_value:
        fv = heads["frame_value"]
        for t in range(T - 1):
            for b in range(B):
                ended = bool(first[t + 1, b])
                if ended and cut[t, b] or not ended and t + 1 == T - 1:
                    continue  # a step limit's cut, or the chunk's last return: unknown
                code = nets.obs_encoder(fv["enc"], variant.arch, preds[t][b:b + 1])
                f_ce.append(twohot_ce(mlp(fv["mlp"], np.asarray(code)[0]), 0.0 if ended else ret[t + 1, b]))
    # the imagined rewards' squared error, averaged within each sign class of the reward, then over the classes
    errors, signs = np.asarray(imag_mse), np.asarray(imag_sign)
    balanced = np.mean([errors[signs == c].mean() for c in (-1.0, 0.0, 1.0) if (signs == c).any()])
    return {"imag_obs_bce": np.mean(imag_bce), "imag_reward_mse": np.mean(imag_mse), "imag_reward_balanced": balanced,
            "reward_twohot": np.mean(r_ce),
            "cont_bce": np.mean(c_bce), "value_twohot": np.mean(v_ce), "frame_value_twohot": np.mean(f_ce or [0.0]),
            "advantage_mse": np.mean(adv or [0.0]),
            "reward_head_mse": np.mean(r_mse),
            "value_mse": np.mean(v_mse)}


@pytest.mark.parametrize("name,steps,stride,truncated,backup", [("reward_prediction", 3, 2, False, "lambda"),
                                                               ("final_proposal", 2, 3, False, "lambda"),
                                                               ("final_proposal", 3, 2, True, "lambda"),
                                                               ("final_proposal", 2, 3, True, "max"),
                                                               ("reward_prediction", 2, 2, True, "frame"),
                                                               ("final_proposal", 3, 3, False, "advantage")])
def test_every_term_equals_a_plain_loop_over_starts_and_steps(name, steps, stride, truncated, backup):
    """Imagined steps stop at the chunk's end and at an episode start; the value's targets are
    λ-returns of the target head's values on the real states (backup "max": Peng's Q(λ), each
    step bootstrapping on the best of the eight buttons pressed with the next real frame); the
    heads score the real steps and every imagined one. An episode its step limit cut
    (`truncated`) goes on: its last step bootstraps on its own state's value. The frame value
    ("frame") learns from each predicted frame the return from the step after, 0 after an end;
    the advantage ("advantage") the return less the mean of the eight buttons' values."""
    variant = make_variant(name, TINY)
    hp = la.LookaheadHParams.create(steps=steps, stride=stride, gamma=0.9, lam=0.8,
                                    backup=backup if backup in la.VALUE_BACKUPS else "lambda",
                                    frame_value=backup == "frame", advantage=backup == "advantage")
    params = la.with_heads(variant, variant.init(jax.random.PRNGKey(3)), jax.random.PRNGKey(4), hp)
    # non-zero heads, and a target copy that differs from the head, so every path counts
    params["lookahead"] = jax.tree.map(lambda x: x + 0.3 * jax.random.normal(jax.random.PRNGKey(x.size), x.shape),
                                       params["lookahead"])
    chunk = _chunk(truncated=truncated)
    hparams = HParams.create(variant, lookahead=hp)
    _, (_, terms, _) = chunk_loss(variant, params, variant.init_carry(B), hparams, chunk)
    want = _by_hand(variant, params, hp, chunk, hparams.loss_weights)
    for key, value in want.items():
        np.testing.assert_allclose(float(terms[key]), value, rtol=2e-4, atol=1e-5, err_msg=key)


def test_the_heads_gradient_into_the_model_is_scaled_by_head_grad():
    """The heads' terms reach the model's parameters times `head_grad`, their own in full."""
    variant = make_variant("reward_prediction", TINY)
    chunk = _chunk(1)
    only = {k: 0.0 for k in HParams.create(variant, lookahead=la.LookaheadHParams.create()).loss_weights}
    only["value_twohot"] = 1.0

    def grads(scale):
        hp = la.LookaheadHParams.create(head_grad=scale)
        params = la.with_heads(variant, variant.init(jax.random.PRNGKey(0)), jax.random.PRNGKey(1), hp)
        params["lookahead"]["value"] = jax.tree.map(lambda x: x + 0.1, params["lookahead"]["value"])
        hparams = HParams.create(variant, lookahead=hp, loss_weights=only)
        return jax.grad(lambda p: chunk_loss(variant, p, variant.init_carry(B), hparams, chunk)[0])(params)

    full, tenth = grads(1.0), grads(0.1)
    lstm = lambda g: g["lstm"]["w_input"]  # noqa: E731
    np.testing.assert_allclose(lstm(tenth), 0.1 * lstm(full), rtol=1e-4, atol=1e-9)
    assert float(jnp.abs(lstm(full)).max()) > 0
    for a, b in zip(jax.tree.leaves(full["lookahead"]["value"]), jax.tree.leaves(tenth["lookahead"]["value"])):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-9)


def test_a_train_step_moves_the_heads_by_their_own_optimiser_and_the_target_after_them():
    variant = make_variant("final_proposal", TINY)
    hp = HParams.create(variant, lr=0.1, lookahead=la.LookaheadHParams.create(target_decay=0.5))
    state = init_state(variant, jax.random.PRNGKey(0), B, hp)
    before = jax.tree.map(np.asarray, state.params["lookahead"])  # the step donates the state
    state, metrics = train_step(variant, state, hp, _chunk(2))
    after = state.params["lookahead"]
    assert not bool(metrics["diverged"])
    # Adam's first step moves each weight by about its rate, whatever the gradient's size
    moved = np.abs(np.asarray(after["cont"]["dense0"]["kernel"] - before["cont"]["dense0"]["kernel"]))
    assert 0.5 * 3e-4 < np.median(moved[moved > 0]) < 1.5 * 3e-4
    want = jax.tree.map(lambda t, v: 0.5 * t + 0.5 * v, before["value_target"], after["value"])
    for a, b in zip(jax.tree.leaves(after["value_target"]), jax.tree.leaves(want)):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
    for term in la.TERMS:
        assert np.isfinite(float(metrics["terms"][term]))


def test_look_ahead_needs_a_model_that_acts_and_refuses_multi_step_feeding():
    with pytest.raises(ValueError, match="has none"):
        la.with_heads(make_variant("main", TINY), {}, jax.random.PRNGKey(0), la.LookaheadHParams.create())
    with pytest.raises(ValueError, match="choose one"):
        HParams.create(make_variant("final_proposal", TINY), feed_every=3, lookahead=la.LookaheadHParams.create())
    with pytest.raises(ValueError, match="lookahead_steps >= 1"):
        RunConfig(variant="final_proposal", learner="world_model", imagined_reward_balanced_weight=0.003)

    with pytest.raises(ValueError, match="value_backup 'max', frame_value_weight 0.0 and advantage_weight 0.0 set "
                                         ".*lookahead_steps >= 1"):
        RunConfig(variant="final_proposal", learner="world_model", value_backup="max")
    with pytest.raises(ValueError, match="value_backup must be one of lambda, max; got 'best'"):
        RunConfig(variant="final_proposal", learner="world_model", lookahead_steps=2, value_backup="best")
