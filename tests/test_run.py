"""Runs a researcher can trust: exact resume after SIGKILL, corrupt and incompatible
checkpoints, the metrics file, the CLI."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cdrl.cli import main as cli_main
from cdrl.runs.checksums import has_checksums

SMALL_RUN = ["--data", "synthetic", "--preset", "tiny", "--episodes", "6", "--episode-steps", "30",
             "--unroll", "8", "--batch", "2", "--lr", "0.3", "--eval-every", "0", "--eval-episodes", "1"]


def _cli(*args):
    return [sys.executable, "-m", "cdrl.cli", *args]


def _records(run_dir: Path) -> list[dict]:
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in lines]
    assert [r["step"] for r in records] == list(range(len(records)))
    return records


def _losses(run_dir: Path) -> list[float]:
    return [r["loss"] for r in _records(run_dir)]


def _finished_checkpoints(ckpt_dir: Path) -> list[int]:
    """Steps of the finished checkpoints: orbax renames '<step>.orbax-checkpoint-tmp-*' to
    '<step>' when its save is complete, and the save then writes the checksums; a checkpoint
    without them (a kill between the two) is unfinished, and a resume skips it."""
    if not ckpt_dir.exists():
        return []
    return sorted(int(p.name) for p in ckpt_dir.iterdir() if p.name.isdigit() and has_checksums(p))


@pytest.mark.default_opt
def test_sigkill_and_resume_give_the_same_losses(tmp_path):
    straight = tmp_path / "straight"
    assert cli_main(["train", "--run-dir", str(straight), *SMALL_RUN, "--steps", "60", "--checkpoint-every", "10"]) == 0

    killed = tmp_path / "killed"
    proc = subprocess.Popen(_cli("train", "--run-dir", str(killed), *SMALL_RUN, "--steps", "100000",
                                 "--checkpoint-every", "10"), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 240
    ckpt = killed / "checkpoints"
    while time.time() < deadline and proc.poll() is None and len(_finished_checkpoints(ckpt)) < 2:
        time.sleep(0.05)
    finished = _finished_checkpoints(ckpt)
    assert proc.poll() is None, "the run ended before it was killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    # The kill landed after at least two finished checkpoints (else the resumed run would
    # start from step 0 and, being deterministic, match anyway).
    assert len(finished) >= 2, f"no finished checkpoint before the kill: {finished}"
    assert (killed / "config.json").exists()
    newest = max(_finished_checkpoints(ckpt))
    assert 20 <= newest < 60
    # The records of the steps before `newest` (the kill may have torn a later line).
    before = [json.loads(line) for line in (killed / "metrics.jsonl").read_text().splitlines()[:newest]]
    assert [r["step"] for r in before] == list(range(newest))

    result = subprocess.run(_cli("train", "--resume", str(killed), "--steps", "60"), capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    a, b = _losses(straight), _losses(killed)
    assert len(a) == len(b) == 60
    assert max(abs(x - y) for x, y in zip(a, b)) <= 1e-6
    # The resumed run started from checkpoint `newest`: the records of the steps before it are
    # still the killed process's own, frames/s (a wall-clock measurement, different had the
    # steps been run again) included.
    assert _records(killed)[:newest] == before


def test_corrupt_checkpoint_falls_back_to_an_older_one(tmp_path, capsys):
    run = tmp_path / "run"
    assert cli_main(["train", "--run-dir", str(run), *SMALL_RUN, "--steps", "20", "--checkpoint-every", "10"]) == 0
    before = _records(run)
    newest = run / "checkpoints" / "20"
    for path in newest.rglob("*"):
        if path.is_file():
            path.write_bytes(b"garbage")
    capsys.readouterr()
    assert cli_main(["train", "--resume", str(run), "--steps", "30"]) == 0
    err = capsys.readouterr().err
    assert "checkpoints/20" in err and "older checkpoint" in err
    after = _records(run)
    assert len(after) == 30
    # It went on from checkpoint 10: steps 0-9 keep their records (frames/s, a wall-clock
    # measurement, included), steps 10-19 were run again from the restored state and give
    # the same losses as the first time.
    assert after[:10] == before[:10]
    assert [r["fps"] for r in after[10:20]] != [r["fps"] for r in before[10:20]]
    assert max(abs(a["loss"] - b["loss"]) for a, b in zip(after[10:20], before[10:20])) <= 1e-6


def test_incompatible_config_is_refused_and_loses_nothing(tmp_path, capsys):
    run = tmp_path / "run"
    assert cli_main(["train", "--run-dir", str(run), *SMALL_RUN, "--steps", "10", "--checkpoint-every", "10"]) == 0
    before = (run / "config.json").read_text()
    metrics_before = (run / "metrics.jsonl").read_text()
    capsys.readouterr()
    assert cli_main(["train", "--resume", str(run), "--lr", "0.01", "--steps", "20"]) == 2
    err = capsys.readouterr().err
    assert "incompatible config" in err and "lr: checkpoint has 0.3, run has 0.01" in err
    assert (run / "config.json").read_text() == before
    assert (run / "metrics.jsonl").read_text() == metrics_before and len(metrics_before.splitlines()) == 10
    assert _finished_checkpoints(run / "checkpoints") == [10]


def test_metrics_file_parses_and_loss_falls(tmp_path):
    run = tmp_path / "run"
    assert cli_main(["train", "--run-dir", str(run), *SMALL_RUN, "--steps", "60", "--checkpoint-every", "30"]) == 0
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    losses = [r["loss"] for r in records]
    assert sum(losses[-10:]) / 10 < 0.8 * sum(losses[:5]) / 5
    assert set(records[0]["ratios"]) >= {"obs_enc/conv0/kernel", "lstm/w_recurrent", "fc/dense0/bias"}
    assert all(r["fps"] > 0 for r in records)
    config = json.loads((run / "config.json").read_text())  # nested by section
    assert config["optim"]["lr"] == 0.3 and config["model"]["variant"] == "main"
    evals = [json.loads(line) for line in (run / "eval.jsonl").read_text().splitlines()]
    assert evals[-1]["step"] == 60 and evals[-1]["bce"] > 0 and evals[-1]["copy_bce"] > 0


def test_cli_rejects_bad_options(tmp_path, capsys):
    assert cli_main(["train", "--run-dir", str(tmp_path / "a"), "--variant", "nope"]) == 2
    assert "unknown variant 'nope'" in capsys.readouterr().err
    assert cli_main(["train", "--run-dir", str(tmp_path / "b"), "--unroll", "0"]) == 2
    assert "unroll must be >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli_main(["train", "--lr", "fast"])


def test_divergence_in_a_run_is_reported_by_group(tmp_path, capsys):
    run = tmp_path / "run"
    code = cli_main(["train", "--run-dir", str(run), *SMALL_RUN, "--lr", "1000", "--steps", "50",
                     "--diverge-threshold", "100"])
    assert code == 2
    err = capsys.readouterr().err
    assert "diverged at step" in err and "worst parameter group" in err and "Last good state saved" in err


def test_eval_policy_needs_a_controller_run(tmp_path, capsys):
    run = tmp_path / "run"
    assert cli_main(["train", "--run-dir", str(run), *SMALL_RUN, "--steps", "2", "--checkpoint-every", "2"]) == 0
    capsys.readouterr()
    assert cli_main(["eval", "--policy", str(run)]) == 2
    assert "has no controller" in capsys.readouterr().err
    assert cli_main(["eval", "--policy", str(tmp_path / "nowhere")]) == 2
    assert "nowhere does not exist" in capsys.readouterr().err


def test_the_readme_python_example_runs(tmp_path, monkeypatch):
    """The README's Python quickstart, as written, trains a run and resumes it."""
    import re

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    code = re.search(r"### Python\n.*?```python\n(.*?)```", readme, re.S).group(1)
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "README.md", "exec"), {})
    assert [r["step"] for r in _records(tmp_path / "runs" / "py")] == list(range(60))


@pytest.mark.e2e
def test_a_second_run_of_the_same_configuration_compiles_nothing(tmp_path):
    """The CLI keeps JAX's compilation cache in --compile-cache: a second process training the
    same configuration finds every program it needs there and adds none; --no-compile-cache
    keeps nothing."""
    cache = tmp_path / "cache"
    # The CLI keeps every program (its default); the suite's own threshold (0.5 s, conftest.py)
    # would let a program compiled in 0.49 s by the first run and 0.51 s by the second be new.
    env = {**os.environ, "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0"}

    def programs(directory: Path) -> set[str]:
        return {p.name for p in directory.iterdir() if not p.name.endswith(("-atime", ".lock"))}

    for name in ("first", "second"):
        subprocess.run(_cli("train", "--run-dir", str(tmp_path / name), *SMALL_RUN, "--steps", "2",
                            "--compile-cache", str(cache)), check=True, capture_output=True, env=env)
        if name == "first":
            compiled = programs(cache)
    assert compiled and programs(cache) == compiled
    subprocess.run(_cli("train", "--run-dir", str(tmp_path / "third"), *SMALL_RUN, "--steps", "2",
                        "--compile-cache", str(tmp_path / "unused"), "--no-compile-cache"), check=True,
                   capture_output=True, env=env)
    assert not (tmp_path / "unused").exists()
