"""Every numeric option of every command tried with zero, a negative number, NaN, infinity and a
word: each value is either accepted by design (`ACCEPTED`, with the reason) or refused with a
message naming the option, exit status 2, nothing written and no traceback; and every command
on bad input ends in a named error, never a traceback.

The commands run in this process (`cdrl.cli.main`). An accepted value must reach the command's
work, which is replaced by a stub raising `Accepted`, so nothing here trains, collects or
compiles: every refusal must come before any of that.
"""
import dataclasses
import json

import pytest

from cdrl.cli import main as cli_main
from cdrl.runs.config import RunConfig

VALUES = ("0", "-1", "nan", "inf", "abc")
NUMERIC = [f.name for f in dataclasses.fields(RunConfig) if f.type in ("int", "float")]
LR_SEARCH_SKIPS = ("lr", "steps", "diverge_threshold")  # lr-search sets these itself

# (option, value) pairs accepted by design, for every command that has the option; every
# other value of every numeric option must be refused.
ACCEPTED = {
    ("lr_warmup", "0"),  # no warm-up
    ("lr_decay_steps", "0"),  # the cosine decay over the run's steps (unused by a constant schedule)
    ("seed", "0"),  # a seed like any other
    ("devices", "0"),  # every device of every process
    ("eval_every", "0"),  # evaluate at the end only
    ("warmup_steps", "0"),  # the reward ascent from the first update
    ("weight_decay", "0"),  # no weight decay
    ("grad_clip", "0"),  # no gradient clipping
    ("momentum", "0"),  # plain SGD
    ("b2", "0"),  # RMS of the last gradient only
    ("ascent", "0"),  # online variants: model learning without the reward ascent
    ("reward_weight", "0"),  # no reward-prediction loss
    ("reward_balanced_weight", "0"),  # no balanced reward term (the default)
    ("noise_std", "0"),  # no exploration noise
    ("value_coef", "0"),  # ppo: no value loss
    ("entropy_coef", "0"),  # ppo: no entropy bonus
    ("gamma", "0"),  # a myopic discount
    ("gae_lambda", "0"),  # one-step advantages
    ("obs_mean", "0"), ("obs_mean", "-1"),  # any finite brightness offset of the encoder's input
    ("lookahead_steps", "0"),  # no look-ahead losses (the default)
    ("lookahead_stride", "0"),  # the look-ahead's starts every K steps (the default)
    ("imagined_frame_weight", "0"), ("reward_head_weight", "0"), ("cont_weight", "0"),  # a look-ahead term off
    ("imagined_reward_balanced_weight", "0"),  # no balanced reward term at the imagined steps (the default)
    ("value_weight", "0"),  # no value head's loss
    ("frame_value_weight", "0"),  # no frame value head (the default)
    ("advantage_weight", "0"),  # no advantage head (the default)
    ("head_grad", "0"),  # the heads learn without moving the model
    ("value_target_decay", "0"),  # the value's target is the head itself
    ("plan_weight", "0"),  # the critic plan's buttons are the controller's
}
# seed 0; a crop at the frame's edge; --devices 0 (every device)
COLLECT_ACCEPTED = {("--seed", "0"), ("--crop", 0, "0"), ("--crop", 1, "0"), ("--devices", "0")}


class Accepted(Exception):
    """Raised by the stubbed work of a command: the command accepted its options."""


def _accept(*args, **kwargs):
    raise Accepted


@pytest.fixture
def stubbed(tmp_path, monkeypatch):
    """Commands run in an empty directory with their work stubbed out; returns the directory."""
    from cdrl.data import collect, gymrec
    from cdrl.runs import sweep, train

    monkeypatch.setattr(train, "train_run", _accept)
    monkeypatch.setattr(sweep, "_sweep_run", _accept)
    monkeypatch.setattr(sweep, "load_episodes", _accept)  # lr-search: after its checks
    monkeypatch.setattr(collect, "write_set", _accept)
    monkeypatch.setattr(gymrec, "write_set", _accept)
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _outcome(argv, capsys) -> tuple[str, str]:
    """('accepted' | 'refused', what the command printed)."""
    capsys.readouterr()
    try:
        code = cli_main(argv)
    except Accepted:
        return "accepted", capsys.readouterr().err
    except SystemExit as exc:  # argparse: a value of the wrong type
        code = exc.code
    out, err = capsys.readouterr()
    assert code == 2, (argv, code, out, err)
    return "refused", out + err


def _check(argv, name: str, accepted: bool, directory, capsys) -> None:
    outcome, printed = _outcome(argv, capsys)
    assert "Traceback" not in printed, printed
    assert outcome == ("accepted" if accepted else "refused"), (argv, printed)
    if not accepted:
        assert name in printed or "--" + name.replace("_", "-") in printed, (argv, printed)  # names the option
    assert list(directory.iterdir()) == [], argv  # nothing written, not even a lock


COMMANDS = {"train": ["train", "--preset", "tiny", "--data", "synthetic"],
            "sweep": ["sweep", "--preset", "tiny", "--data", "synthetic"],
            "lr-search": ["lr-search", "--preset", "tiny", "--data", "synthetic"]}


@pytest.mark.parametrize("command", COMMANDS)
def test_every_run_option_is_accepted_by_design_or_refused_by_name(stubbed, capsys, command):
    names = [n for n in NUMERIC if not (command == "lr-search" and n in LR_SEARCH_SKIPS)]
    for name in names:
        for value in VALUES:
            _check([*COMMANDS[command], "--" + name.replace("_", "-"), value], name, (name, value) in ACCEPTED,
                   stubbed, capsys)


@pytest.mark.parametrize("option", ["--probe-steps", "--threshold", "--candidates"])
def test_lr_search_options_are_refused_by_name(stubbed, capsys, option):
    for value in VALUES:
        _check([*COMMANDS["lr-search"], option, value], option.lstrip("-").replace("-", "_").split("_")[0],
               False, stubbed, capsys)


@pytest.mark.parametrize("option", ["--episodes", "--horizon", "--context", "--games", "--every", "--video-seed"])
def test_eval_options_are_refused_by_name(stubbed, capsys, option):
    for value in VALUES:  # before the run is read: R does not exist
        if option != "--video-seed":
            _check(["eval", "R", option, value], option[2:], False, stubbed, capsys)
        elif value != "0":  # game 0 is a game
            _check(["eval", "--policy", "R", "--video", option, value], option[2:], False, stubbed, capsys)


@pytest.mark.parametrize("option", ["--episodes", "--seed", "--episode-steps", "--obs-size", "--batch-size",
                                    "--devices", "--max-filter"])
def test_collect_options_are_accepted_by_design_or_refused_by_name(stubbed, capsys, option):
    for value in VALUES:
        _check(["collect", "D", option, value], option, (option, value) in COLLECT_ACCEPTED, stubbed, capsys)


@pytest.mark.parametrize("position", range(4))
def test_collect_crop_is_accepted_by_design_or_refused_by_name(stubbed, capsys, position):
    for value in VALUES:
        crop = ["0", "0", "400", "400"]  # fits CartPole's 400 x 600 frames, a multiple of 16
        crop[position] = value
        _check(["collect", "D", "--env", "CartPole-v1", "--obs", "render", "--obs-size", "16", "--crop", *crop],
               "--crop", ("--crop", position, value) in COLLECT_ACCEPTED, stubbed, capsys)


def test_the_sweep_of_values_covers_every_numeric_option_of_every_command():
    """The options these tests try are exactly the parser's numeric ones: one added later is
    tried too (or this fails)."""
    import argparse

    from cdrl.cli import build_parser

    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices
    numeric = {name: {a.option_strings[0] for a in parser._actions if a.type in (int, float)}
               for name, parser in commands.items()}
    run_options = {"--" + n.replace("_", "-") for n in NUMERIC}
    assert numeric["train"] == numeric["sweep"] == run_options
    assert numeric["lr-search"] == (run_options - {"--lr", "--steps", "--diverge-threshold"}
                                    | {"--probe-steps", "--threshold", "--candidates"})
    assert numeric["eval"] == {"--episodes", "--horizon", "--context", "--games", "--every", "--video-seed"}
    assert numeric["collect"] == {"--episodes", "--seed", "--episode-steps", "--obs-size", "--crop", "--batch-size",
                                  "--devices", "--max-filter"}
    assert numeric["plot"] == numeric["variants"] == set()
    assert {name for name, _ in ACCEPTED} <= set(NUMERIC)


def _bad_inputs(t):
    """Bad input to every command (directories that are not what the command reads)."""
    (t / "file").write_text("not a directory\n")
    (t / "garbage").mkdir()
    (t / "garbage" / "config.json").write_text("{")
    (t / "nan").mkdir()
    (t / "nan" / "config.json").write_text(json.dumps({**dataclasses.asdict(RunConfig()), "lr": float("nan")}))
    (t / "records").mkdir()
    (t / "records" / "config.json").write_text(json.dumps(dataclasses.asdict(RunConfig())))
    (t / "records" / "metrics.jsonl").write_text("[1]\n")
    return {
        "train --resume of a file": (["train", "--resume", "file"], "cannot resume"),
        "train --resume of a garbage config": (["train", "--resume", "garbage"], "is not a valid run config"),
        "train --resume of a NaN config": (["train", "--resume", "nan"], "lr must be a finite number, got nan"),
        "train --allow-data-change without --resume": (["train", "--allow-data-change"],
                                                        "--allow-data-change is for --resume"),
        "sweep --resume of a file": (["sweep", "--resume", "file"], "sweep directory file is a file"),
        "eval of a garbage config": (["eval", "garbage"], "is not a valid run config"),
        "eval --policy of nothing": (["eval", "--policy", "nowhere"], "nowhere does not exist"),
        "eval --imagination of nothing": (["eval", "--imagination", "nowhere"], "nowhere does not exist"),
        "eval --video without --policy": (["eval", "--video", "run"], "--video records a game of a learned policy"),
        "plot of a file": (["plot", "file"], "run directory file is a file"),
        "plot of a NaN config": (["plot", "nan"], "lr must be a finite number"),
        "plot of metrics that are not records": (["plot", "records"], "line 1 is not a record of a step"),
        "collect into a file": (["collect", "file", "--episodes", "1", "--obs-size", "16"], "file"),
        "collect a game that fails on its options": (
            ["collect", "g", "--env", "FrozenLake-v1", "--obs", "render", "--env-kwargs", "map_name=9x9"],
            "gymnasium cannot make 'FrozenLake-v1' with --env-kwargs"),
        "collect a game that fails when it steps": (
            ["collect", "g", "--env", "Pendulum-v1", "--obs", "render", "--obs-size", "16", "--env-kwargs", "g=abc"],
            "gymnasium game 'Pendulum-v1' failed in its first reset and step: TypeError"),
    }


def test_no_command_answers_bad_input_with_a_traceback(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    cases = _bad_inputs(tmp_path)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    for case, (argv, message) in cases.items():
        outcome, printed = _outcome(argv, capsys)
        assert outcome == "refused" and "Traceback" not in printed, (case, printed)
        assert message in printed, (case, printed)
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before  # nothing written
