"""The imagination probe (`cdrl.evaluation.imagination_probe`, `cdrl eval --imagination`): its
scores against direct computations, an oracle and a constant model on a game whose answer is
known, the play it follows against the model stepped by hand, and the video of imagination."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import games
from cdrl.analysis import imagination_video as iv
from cdrl.data.frames import model_obs
from cdrl.evaluation import imagination_probe as ip
from cdrl.models import make_variant
from cdrl.models.arch import TINY
from cdrl.models.base import StepInput
from cdrl.models.controller import FinalProposal
from cdrl.training import lookahead as la
from envs.policies import privileged_policy


def _rewards(seed, starts=200, horizon=6):
    rng = np.random.default_rng(seed)
    return rng.choice([0.0, 0.5, -0.25], size=(starts, len(ip.SEQUENCES), horizon), p=[0.8, 0.1, 0.1])


def test_a_perfect_imagination_agrees_on_every_start_and_a_reversed_one_on_none():
    real = _rewards(0)
    got = ip.scores(real, real, [6])["6"]
    assert got["corr_all"] == pytest.approx(1.0)
    assert got["corr_steer"] == pytest.approx(1.0)
    assert got["best_steer_agree"] == 1.0
    assert got["accelerate_gap_imagined"] == pytest.approx(got["accelerate_gap_real"])
    flipped = ip.scores(real, -real, [6])["6"]
    assert flipped["corr_steer"] == pytest.approx(-1.0)
    assert flipped["best_steer_agree"] == 0.0  # the real best is the imagined worst


def test_scores_equal_a_direct_loop_over_the_starts():
    real, imagined = _rewards(1), _rewards(2)
    got = ip.scores(real, imagined, [1, 4])
    for k in (1, 4):
        r, i = real[..., :k].sum(-1), imagined[..., :k].sum(-1)
        agree, counted, dr, di, firsts, straight = 0.0, 0, [], [], [], 0
        for rs, is_ in zip(r, i):
            steer_r, steer_i = rs[:ip.STEER], is_[:ip.STEER]
            if np.sum(steer_r == steer_r.max()) != 1:
                continue  # no one best direction: the start is left out
            counted += 1
            tied = [j for j in range(ip.STEER) if steer_i[j] == steer_i.max()]
            agree += (int(np.argmax(steer_r)) in tied) / len(tied)
            firsts.append(int(np.argmax(steer_r)))
            straight += int(np.argmax(steer_r) == 0)
            dr += list(steer_r - steer_r.mean())
            di += list(steer_i - steer_i.mean())
        assert got[str(k)]["starts_with_one_best"] == counted
        assert got[str(k)]["best_steer_agree"] == pytest.approx(agree / counted)
        assert got[str(k)]["always_straight_agree"] == pytest.approx(straight / counted)
        assert got[str(k)]["corr_steer"] == pytest.approx(np.corrcoef(dr, di)[0, 1])
        assert got[str(k)]["best_share_real"] == pytest.approx([firsts.count(j) / counted for j in range(ip.STEER)])
        assert got[str(k)]["corr_all"] == pytest.approx(np.corrcoef(r.ravel(), i.ravel())[0, 1])
        assert got[str(k)]["accelerate_gap_real"] == pytest.approx(np.mean(r[:, 3] - r[:, 0]))


def test_the_value_at_the_end_changes_the_ranking_as_by_hand():
    """One start, two steps, gamma 0.5. Real 2-step returns: straight 1, turn0 2, turn1 0.
    Imagined rewards alone rank straight first (0.5 > 0.25 > 0); with the value after step 1,
    straight scores 0.5 + 0.5 * 0 = 0.5, turn0 0.25 + 0.5 * 1.0 = 0.75, turn1 0 + 0.5 * 0.2 = 0.1:
    turn0, the real best. After step 2 (0.25 a step more for straight): straight 0.75 + 0.25 * 0,
    turn0 0.25 + 0.25 * 2.0 = 0.75, a tie of two, half a vote."""
    real = np.array([[[1.0, 0.0], [1.0, 1.0], [0.0, 0.0], [0.0, 0.0]]])
    imagined = np.array([[[0.5, 0.25], [0.25, 0.0], [0.0, 0.0], [0.0, 0.0]]])
    values = np.array([[[0.0, 0.0], [1.0, 2.0], [0.2, 0.0], [0.0, 0.0]]])
    with_value = ip.horizon_scores(real, imagined, values, 0.5, [1, 2])
    assert with_value["1"]["best_steer_agree"] == 1.0
    assert with_value["1"]["best_share_imagined"] == [0.0, 1.0, 0.0]
    assert with_value["2"]["best_steer_agree"] == 0.5
    assert with_value["2"]["always_straight_agree"] == 0.0
    without = ip.horizon_scores(real, imagined, np.zeros_like(values), 0.5, [1])
    assert without["1"]["best_steer_agree"] == 0.0
    assert without["1"]["best_share_imagined"] == [1.0, 0.0, 0.0]


def test_auc_counts_the_pairs_a_positive_wins():
    # positives 0.4 and 0.8 against negatives 0.1, 0.35, 0.4: 0.4 wins 2 and ties 1, 0.8 wins 3
    assert ip.auc([0.1, 0.4, 0.35, 0.8, 0.4], [0, 1, 0, 1, 0]) == pytest.approx(5.5 / 6)
    assert ip.auc([3.0, 2.0, 1.0], [0, 1, 1]) == 0.0
    assert ip.auc([1.0, 1.0], [0, 1]) == 0.5
    assert ip.auc([1.0, 2.0], [1, 1]) is None
    rng = np.random.default_rng(0)
    scores, labels = rng.integers(0, 5, 60).astype(float), rng.random(60) < 0.3
    pos, neg = scores[labels], scores[~labels]
    pairs = np.mean([(p > n) + 0.5 * (p == n) for p in pos for n in neg])
    assert ip.auc(scores, labels) == pytest.approx(pairs)


def test_discounted_returns_and_the_value_correlation():
    np.testing.assert_allclose(ip.discounted_returns(np.array([1.0, 0.0, 2.0]), 0.5), [1.5, 1.0, 2.0])
    np.testing.assert_allclose(ip.discounted_returns(np.array([[0.0, 4.0], [1.0, 1.0]]), 0.5), [[2.0, 4.0], [1.5, 1.0]])
    assert ip.corr([1.0, 1.0, 1.0], [0.0, 1.0, 2.0]) is None
    assert ip.corr([1.0], [2.0]) is None
    assert ip.corr([0.0, 1.0, 3.0], [1.0, 2.0, 4.0]) == pytest.approx(1.0)


def test_the_sequences_are_three_ways_to_steer_without_accelerating_then_one_that_accelerates():
    buttons = np.asarray(list(ip.SEQUENCES.values()))
    assert ip.STEER == 3 and buttons.shape == (4, 3)
    assert not buttons[:ip.STEER, 2].any() and buttons[ip.STEER, 2] == 1.0  # button 2: accelerate
    assert len({tuple(b) for b in buttons[:ip.STEER, :2]}) == 3


class Oracle(FinalProposal):
    """final_proposal whose imagined reward is `params["oracle"]` times `games.TurnOneSlither`'s reward
    plus (1 - it) times 0.3: the game's own reward at 1, a constant at 0 (one program for both)."""

    def imagine_step(self, params, carry, frame, action):
        carry, out = super().imagine_step(params, carry, frame, action)
        w = params["oracle"]
        return carry, {**out, "reward": w * action[:, 1] * (1.0 - action[:, 0]) + (1.0 - w) * 0.3}


def _turn_one():
    _, env_params = games.test_game()
    game = games.TurnOneSlither(**games.SIZES)
    variant = Oracle(TINY)
    return game, env_params, variant, variant.init(jax.random.PRNGKey(0))


def test_an_oracle_names_the_real_best_at_every_start_and_a_constant_at_a_third():
    """On `games.TurnOneSlither`, turn1 is the real best from every state. An imagination whose rewards
    are the game's ranks it first at every start, its returns correlate 1 with the real ones and
    its rewards tell a pellet (a rewarded step) from none perfectly. A constant imagination has no
    correlation and ties three ways: a third of a vote at every start."""
    game, env_params, variant, params = _turn_one()
    run = lambda w: ip.probe(variant, {**params, "oracle": jnp.float32(w)}, game, env_params, None, 0.9,  # noqa: E731
                             max_steps=games.MAX_STEPS, games=2, every=8, horizon=3, ks=(1, 3))
    oracle, constant = run(1.0), run(0.0)
    assert oracle["starts"] == constant["starts"] == 2 * (games.MAX_STEPS // 8 - 1)
    assert oracle["reward_source"] == "variant" and not oracle["value_head"] and oracle["value_corr"] is None
    assert list(oracle["by_horizon"]) == ["1", "3"]  # the horizons up to 3 steps
    for got in (oracle["by_steps"]["3"], oracle["by_horizon"]["1"], oracle["by_horizon"]["3"]):
        assert got["best_steer_agree"] == 1.0
        assert got["corr_all"] == pytest.approx(1.0) and got["corr_steer"] == pytest.approx(1.0)
        assert got["always_straight_agree"] == 0.0 and got["best_share_real"] == [0.0, 0.0, 1.0]
    assert oracle["by_steps"]["3"]["mean_real"] == [0.0, 0.0, 3.0, 0.0]
    assert oracle["by_steps"]["3"]["mean_imagined"] == [0.0, 0.0, 3.0, 0.0]
    assert oracle["reward_auc"] == {"straight": [None] * 3, "all": [1.0] * 3}
    for got in (constant["by_steps"]["3"], constant["by_horizon"]["3"]):
        assert got["corr_all"] is None and got["corr_steer"] is None
        assert got["best_steer_agree"] == pytest.approx(1 / 3)
        assert got["best_share_imagined"] == pytest.approx([1 / 3] * 3)
    assert constant["reward_auc"]["all"] == [0.5] * 3


def test_reward_from_picks_the_head_that_scores_the_imagined_steps():
    """The oracle with look-ahead heads beside it: by default the heads score the imagined steps
    (their last layer starts at zero, so every sequence ties); `reward_from="variant"` takes the
    oracle's own rewards and names turn1 at every start. A head the run lacks is refused."""
    game, env_params, variant, params = _turn_one()
    hp = la.LookaheadHParams.create(steps=2)
    params = la.with_heads(variant, {**params, "oracle": jnp.float32(1.0)}, jax.random.PRNGKey(1), hp)
    run = lambda source: ip.probe(variant, params, game, env_params, hp, 0.9, max_steps=games.MAX_STEPS,  # noqa: E731
                                  games=1, every=8, horizon=3, ks=(3,), reward_from=source)
    heads, own = run(None), run("variant")
    assert heads["reward_source"] == "lookahead" and own["reward_source"] == "variant"
    assert heads["by_steps"]["3"]["mean_imagined"] == pytest.approx([0.0] * 4, abs=1e-6)
    assert own["by_steps"]["3"]["mean_imagined"] == [0.0, 0.0, 3.0, 0.0]
    assert own["by_steps"]["3"]["best_steer_agree"] == 1.0
    with pytest.raises(ValueError, match="no look-ahead reward head"):
        ip.reward_source(variant, None, "lookahead")
    with pytest.raises(ValueError, match="no reward head of its own"):
        ip.reward_source(make_variant("action_loop", TINY), hp, "variant")


def test_the_value_on_recorded_play_equals_a_step_by_step_loop():
    """`data_value_corr`: V(h_t) after each recorded step, fed teacher-forced from the episode's
    start, against Σ_k γ^k r_{t+1+k} up to the episode's end, pooled over the episodes."""
    from cdrl.data.synthetic import synthetic_episodes

    variant = make_variant("final_proposal", TINY)
    hp = la.LookaheadHParams.create(steps=2)
    params = la.with_heads(variant, variant.init(jax.random.PRNGKey(0)), jax.random.PRNGKey(1), hp)
    value = params["lookahead"]["value"]
    value = {**value, "dense1": jax.tree.map(lambda x: jax.random.normal(jax.random.PRNGKey(2), x.shape),
                                             value["dense1"])}
    params = {**params, "lookahead": {**params["lookahead"], "value": value}}
    episodes = synthetic_episodes(2, 9, TINY.image_size, seed=3)
    rng = np.random.default_rng(0)
    episodes = [dataclasses.replace(ep, rewards=rng.normal(size=len(ep.rewards)).astype(np.float32)) for ep in episodes]
    gamma = 0.8
    got, n = ip.data_value_corr(variant, params, hp, episodes, gamma)
    values, returns = [], []
    for ep in episodes:
        carry = variant.init_carry(1)
        for t in range(len(ep.rewards) - 1):
            frame = jnp.asarray(np.asarray(ep.frames[t], np.float32) / (255.0 if ep.frames.dtype == np.uint8 else 1.0))
            carry, _ = variant.step(params, carry, StepInput(obs=frame[None], action=jnp.asarray(ep.actions[t:t + 1]),
                                                             is_first=jnp.asarray([t == 0])))
            values.append(float(la.value(params["lookahead"], variant.features(carry), hp)[0]))
            returns.append(sum(gamma ** k * float(r) for k, r in enumerate(ep.rewards[t + 1:])))
    assert n == len(values) == 2 * 8
    assert got == pytest.approx(float(np.corrcoef(values, returns)[0, 1]), abs=1e-4)


def test_the_video_shows_each_start_and_step_real_beside_imagined(tmp_path):
    """Two starts of three steps: six frames. The tiny preset's 16-pixel frames are drawn 6 times
    as large: 2 * 96 + 3 * 4 = 204 pixels wide, 14 + 4 * (96 + 24 + 4) = 510 high; the first
    frame's top left holds the real frame after one step straight on."""
    from PIL import Image

    game, env_params, variant, params = _turn_one()
    watched = iv.watch(variant, {**params, "oracle": jnp.float32(1.0)}, game, env_params, None, starts=2, every=8,
                       steps=3)
    np.testing.assert_array_equal(watched["real"][:, 2], 1.0)  # turn1 pays 1 a step
    np.testing.assert_array_equal(watched["imagined"][:, 2], 1.0)
    path = iv.write_gif(iv.frame_images(watched, with_value=False), tmp_path / "imagination.gif", iv.FRAME_MS)
    with Image.open(path) as gif:
        assert (gif.n_frames, gif.size) == (6, (204, 510))
        first = np.asarray(gif.convert("L"))
    real = np.round(np.clip(watched["real_frames"][0, 0, 0], 0, 1) * 255.0)
    np.testing.assert_allclose(first[iv.HEADER:iv.HEADER + 96:6, iv.PAD:iv.PAD + 96:6], real, atol=1)


def test_the_followed_model_takes_the_frame_and_the_buttons_executed_there():
    """The followed model's state after step t equals the model stepped by hand on (o_t, a_t),
    a_t the buttons executed at o_t (with no exploration: the privileged policy's), as recorded
    data sets and acting controllers give them; the step's reward is the game's."""
    g, env_params = games.test_game()
    variant = make_variant("final_proposal", TINY)
    params = variant.init(jax.random.PRNGKey(0))
    body = ip.follow_step(variant, params, g, env_params, 0.0)
    c0 = ip.start(variant, g, env_params, jax.random.PRNGKey(3))
    h, label, alive, frames, rewards = jax.jit(lambda c: jax.lax.scan(body, c, None, length=8))(c0)[1]
    assert bool(alive.all())

    state, obs, carry, first, key, _, _ = c0
    privileged = privileged_policy(g)
    for t in range(8):
        key, k_policy, _, k_env = jax.random.split(key, 4)
        buttons, _ = privileged.step(k_policy, None, obs, state, env_params)
        np.testing.assert_array_equal(label[t], buttons)
        np.testing.assert_allclose(frames[t], model_obs(obs, variant.arch), atol=1e-6)
        carry, _ = variant.step(params, carry, StepInput(obs=model_obs(obs, variant.arch)[None],
                                                         action=buttons[None], is_first=jnp.array([t == 0])))
        np.testing.assert_allclose(h[t], variant.features(carry)[0], rtol=1e-5, atol=1e-5)
        obs, state, reward, *_ = g.step(k_env, state, buttons, env_params)
        assert float(rewards[t]) == float(reward)


def _write_run(path, **options):
    from cdrl.runs.config import RunConfig
    from cdrl.runs.rundir import RunDir

    RunDir(path).write_config(RunConfig(preset="tiny", **options))
    return str(path)


@pytest.mark.parametrize("options, says", [
    ({"variant": "action_loop", "learner": "world_model"}, "no reward head"),
    ({"variant": "final_proposal", "learner": "world_model", "data": "/nowhere"}, "not the built-in game"),
    ({"variant": "main"}, "takes no actions"),
    ({"learner": "ppo"}, "no world model"),
], ids=["no-reward-head", "data-set", "observation-variant", "ppo"])
def test_cdrl_eval_imagination_names_a_run_it_cannot_probe(tmp_path, capsys, options, says):
    from cdrl.cli import main

    assert main(["eval", "--imagination", _write_run(tmp_path / "run", **options), "--no-compile-cache"]) == 2
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err


@pytest.mark.e2e
def test_cdrl_eval_imagination_writes_its_figures_and_video(tmp_path, capsys):
    """A run of final_proposal with look-ahead heads (its value head given random last weights,
    so that its values vary): the JSON holds every figure, the value's correlation among them,
    and the GIF one frame per step of its first four starts (of the five a 60-step game leaves at 10
    steps apart)."""
    from PIL import Image

    from cdrl.cli import main
    from cdrl.runs.config import RunConfig
    from cdrl.runs.rundir import RunDir
    from cdrl.training.step import init_state

    cfg = RunConfig(variant="final_proposal", learner="world_model", preset="tiny", lookahead_steps=2,
                    episode_steps=60)
    variant = make_variant(cfg.variant, cfg.arch)
    state = init_state(variant, jax.random.PRNGKey(0), cfg.batch, cfg.hparams(variant))
    value = state.params["lookahead"]["value"]
    value = {**value, "dense1": jax.tree.map(lambda x: jax.random.normal(jax.random.PRNGKey(1), x.shape),
                                             value["dense1"])}
    state = state.replace(params={**state.params, "lookahead": {**state.params["lookahead"], "value": value}})
    run = RunDir(tmp_path / "run")
    run.open(cfg, state, resume=False).checkpoints.save(0, state, {"step": 0})

    assert main(["eval", "--imagination", str(run.path), "--games", "2", "--every", "10", "--no-compile-cache"]) == 0
    out = capsys.readouterr().out
    assert "value_corr" in out and "wrote" in out
    result = json.loads((run.path / "imagination.json").read_text())
    assert 0 < result["starts"] <= 2 * 5 and result["value_head"] and result["gamma"] == cfg.gamma
    assert result["reward_source"] == "lookahead"
    assert isinstance(result["value_corr"], float) and 0 < result["value_states"] <= 2 * 50
    assert isinstance(result["value_corr_data"], float) and result["value_states_data"] > 0
    assert list(result["by_horizon"]) == ["1", "3", "5", "15"] and list(result["by_steps"]) == ["1", "5", "15"]
    assert len(result["reward_auc"]["straight"]) == len(result["reward_auc"]["all"]) == 15
    with Image.open(run.path / "imagination.gif") as gif:
        assert gif.n_frames == 4 * 15
