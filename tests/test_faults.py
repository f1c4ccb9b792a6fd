"""Fault injection: what a run, a sweep and a data set survive (the README's table).

One writer per directory (a second is refused with the holder's pid; a killed holder's lock
never blocks; readers work meanwhile), SIGKILL during a collection, a sweep and a checkpoint
write, a full disk during a checkpoint or an episode write, a torn metrics line, and bad
input to the CLI and the API. Kill tests wait for a finished checkpoint (or episode) before
killing, so they cannot pass without the fault having happened.
"""
import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cdrl.cli import main as cli_main
from cdrl.runs.checksums import has_checksums
from cdrl.data.lock import LOCK_NAME, DirLock, LockedError
from cdrl.training.loop import Job, Plan, Sink, host_loop

TINY_RUN = ["--data", "synthetic", "--preset", "tiny", "--episodes", "6", "--episode-steps", "30",
            "--unroll", "8", "--batch", "2", "--lr", "0.3", "--eval-every", "0", "--eval-episodes", "1"]


def _cli(*args):
    return [sys.executable, "-m", "cdrl.cli", *args]


def _start(*args) -> subprocess.Popen:
    return subprocess.Popen(_cli(*args), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _wait_for(proc: subprocess.Popen, ready, what: str, timeout: float = 240.0):
    """Poll `ready()` until it is true while `proc` runs; fail if it ends first."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        if ready():
            return
        if proc.poll() is not None:
            pytest.fail(f"the process ended before {what}: {proc.stderr.read()}")
        time.sleep(0.05)
    proc.kill()
    pytest.fail(f"timed out waiting for {what}")


def _kill(proc: subprocess.Popen) -> None:
    assert proc.poll() is None, "the process ended before it was killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    proc.stderr.close()


def _finished_checkpoints(ckpt_dir: Path) -> list[int]:
    """Steps of the finished checkpoints: orbax renames '<step>.orbax-checkpoint-tmp-*' to
    '<step>' when its save is complete, and the save then writes the checksums; a checkpoint
    without them (a kill between the two) is unfinished, and a resume skips it."""
    if not ckpt_dir.exists():
        return []
    return sorted(int(p.name) for p in ckpt_dir.iterdir() if p.name.isdigit() and has_checksums(p))


def _records(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


# ---- one writer per directory

def test_dir_lock_refuses_a_second_holder_and_outlives_no_killed_one(tmp_path):
    with DirLock(tmp_path / "d", "run directory"):
        assert (tmp_path / "d" / LOCK_NAME).read_text().strip() == str(os.getpid())
        with pytest.raises(LockedError, match=rf"directory .*/d is in use by pid {os.getpid()}") as info:
            DirLock(tmp_path / "d").acquire()
        assert info.value.pid == os.getpid()
    DirLock(tmp_path / "d").acquire().release()  # released: free again

    # A holder killed with SIGKILL leaves its pid in the file but not the lock.
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from cdrl.data.lock import DirLock; "
        f"DirLock({str(tmp_path / 'k')!r}).acquire(); print('held', flush=True); time.sleep(600)")],
        stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    with pytest.raises(LockedError, match=f"pid {holder.pid}"):
        DirLock(tmp_path / "k").acquire()
    os.kill(holder.pid, signal.SIGKILL)
    holder.wait()
    holder.stdout.close()
    assert (tmp_path / "k" / LOCK_NAME).read_text().strip() == str(holder.pid)
    lock = DirLock(tmp_path / "k").acquire()
    assert (tmp_path / "k" / LOCK_NAME).read_text().strip() == str(os.getpid())
    lock.release()


@pytest.mark.e2e
def test_a_second_writer_is_refused_while_readers_work(tmp_path, capsys):
    run = tmp_path / "run"
    proc = _start("train", "--run-dir", str(run), *TINY_RUN, "--steps", "100000", "--checkpoint-every", "5")
    _wait_for(proc, lambda: len(_finished_checkpoints(run / "checkpoints")) >= 1, "a checkpoint")
    capsys.readouterr()
    # Writers: a resume of the same directory, and a new run in it.
    assert cli_main(["train", "--resume", str(run), "--steps", "50"]) == 2
    err = capsys.readouterr().err
    assert f"run directory {run} is in use by pid {proc.pid}" in err
    assert cli_main(["train", "--run-dir", str(run), *TINY_RUN, "--steps", "5"]) == 2
    assert f"pid {proc.pid}" in capsys.readouterr().err
    # Readers: the evaluation table and the figures, from complete records only.
    assert cli_main(["eval", str(run)]) == 0
    rows = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert rows[0]["steps"] >= 5
    assert cli_main(["plot", str(run), "--out", str(tmp_path / "plots")]) == 0
    assert (tmp_path / "plots" / "loss.png").stat().st_size > 0
    _kill(proc)
    # The killed writer's lock does not block the resume.
    assert (run / LOCK_NAME).read_text().strip() == str(proc.pid)
    steps = max(_finished_checkpoints(run / "checkpoints")) + 3
    assert cli_main(["train", "--resume", str(run), "--steps", str(steps)]) == 0
    assert [r["step"] for r in _records(run / "metrics.jsonl")] == list(range(steps))


def test_a_reader_lists_again_when_the_writer_rotates_a_checkpoint_away_mid_read(tmp_path):
    """The race behind `plot` beside a live run: the reader lists the checkpoints, the writer
    saves a newer one and its rotation removes the one the reader is about to read."""
    import numpy as np
    from cdrl.runs.checkpoint import Checkpoints

    state = {"w": np.arange(4.0, dtype=np.float32)}
    writer = Checkpoints(tmp_path / "ck", keep=1)
    writer.save(1, state, {"step": 1})
    reader = Checkpoints(tmp_path / "ck", read_only=True)
    read_meta = reader.read_meta

    def writer_saves_first(step):
        if step == 1:
            writer.save(2, {"w": state["w"] + 1}, {"step": 2})
            assert not (tmp_path / "ck" / "1").exists()
        return read_meta(step)

    reader.read_meta = writer_saves_first
    restored, meta, warnings = reader.restore_latest_good(state)
    assert meta["step"] == 2 and warnings == []
    np.testing.assert_array_equal(restored["w"], state["w"] + 1)
    assert reader.steps() == [2]


def test_a_sweep_locks_its_configurations(tmp_path, capsys):
    sweep = tmp_path / "sweep"
    proc = _start("sweep", "--run-dir", str(sweep), *TINY_RUN, "--lr", "0.3", "0.1", "--steps", "100000",
                  "--checkpoint-every", "5")
    config = sweep / "lr0.1-mom0.9-seed0-thr1000"
    _wait_for(proc, lambda: (config / "config.json").exists(), "the configurations' directories")
    capsys.readouterr()
    assert cli_main(["train", "--resume", str(config), "--steps", "50"]) == 2
    assert f"run directory {config} is in use by pid {proc.pid}" in capsys.readouterr().err
    _kill(proc)


def test_a_collection_locks_its_data_set(tmp_path):
    from cdrl.data.collect import collect

    out = tmp_path / "data"
    proc = _start("collect", str(out), "--episodes", "400", "--episode-steps", "30", "--obs-size", "16")
    _wait_for(proc, lambda: (out / LOCK_NAME).exists() and (out / LOCK_NAME).read_text().strip() == str(proc.pid),
              "the collection's lock")
    with pytest.raises(LockedError, match=rf"data set {out} is in use by pid {proc.pid}"):
        collect(out, 400, max_steps=30, obs_size=16)
    _kill(proc)


# ---- data checked before training

def _episodes(n: int, length: int = 30, size: int = 16, action_dim: int = 3, seed: int = 0):
    import numpy as np

    from cdrl.data.episode import Episode

    rng = np.random.default_rng(seed)
    return [Episode(frames=rng.integers(0, 256, (length + i, size, size), dtype=np.uint8),
                    actions=rng.uniform(0, 1, (length + i, action_dim)).astype(np.float32),
                    rewards=rng.normal(size=length + i).astype(np.float32)) for i in range(n)]


def _dataset(path: Path, n: int = 8, **kwargs) -> Path:
    from cdrl.data.writer import save_dataset

    save_dataset(path, _episodes(n, **kwargs), test_fraction=0.25)
    return path


def _member_data(path: Path, name: str) -> tuple[int, int]:
    """(offset, size) of member `name`'s stored bytes inside the zip `path`."""
    import struct
    import zipfile

    with open(path, "rb") as f, zipfile.ZipFile(f) as z:
        info = z.getinfo(name)
        f.seek(info.header_offset + 26)
        n, m = struct.unpack("<HH", f.read(4))
        return info.header_offset + 30 + n + m, info.compress_size


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _flip_frame_byte(path: Path) -> None:
    offset, size = _member_data(path, "frames.npy")
    data = bytearray(path.read_bytes())
    data[offset + size // 2] ^= 0xFF
    path.write_bytes(bytes(data))


def _rewrite(path: Path, **arrays) -> None:
    import numpy as np

    with np.load(path) as old:
        new = {k: old[k] for k in old.files}
    new.update(arrays)
    new = {k: v for k, v in new.items() if v is not None}
    with open(path, "wb") as f:
        np.savez(f, **new)


def _shorter(path):
    import numpy as np

    with np.load(path) as d:
        _rewrite(path, frames=d["frames"][:-1], actions=d["actions"][:-1], rewards=d["rewards"][:-1])


def _bigger_frames(path):
    import numpy as np

    with np.load(path) as d:
        _rewrite(path, frames=np.zeros((len(d["frames"]), 8, 8), np.uint8))


def _more_actions(path):
    import numpy as np

    with np.load(path) as d:
        _rewrite(path, actions=np.zeros((len(d["actions"]), 4), np.float32))


def _actions_out_of_range(path):
    import numpy as np

    with np.load(path) as d:
        _rewrite(path, actions=d["actions"] + 1.5)


def _float64_rewards(path):
    import numpy as np

    with np.load(path) as d:
        _rewrite(path, rewards=d["rewards"].astype(np.float64))


BAD_FILES = {
    "truncated": (_truncate, "is truncated or corrupt"),
    "flipped byte in the frames": (_flip_frame_byte, "is truncated or corrupt"),
    "not a zip": (lambda p: p.write_bytes(b"hello"), "is truncated or corrupt"),
    "missing": (lambda p: p.unlink(), "is missing"),
    "no rewards": (lambda p: _rewrite(p, rewards=None), r"lacks arrays \['rewards'\]"),
    "fewer frames than the manifest": (_shorter, "the manifest says 31 frames"),
    "other frame size": (_bigger_frames, "frames are 8x8, the manifest says 16x16"),
    "more action values": (_more_actions, "actions have 4 values, the manifest says 3"),
    "actions out of [0, 1]": (_actions_out_of_range, r"actions are not finite values in \[0, 1\]"),
    "float64 rewards": (_float64_rewards, r"rewards are float64 \(31,\), expected float32"),
}


@pytest.mark.parametrize("kind", BAD_FILES)
def test_verify_names_a_bad_episode_file(tmp_path, kind):
    from cdrl.data.store import DatasetError, EpisodeDataset

    data = _dataset(tmp_path / "data")
    EpisodeDataset(data, "all").verify()  # intact
    bad = data / "episode_000001.npz"
    damage, message = BAD_FILES[kind]
    damage(bad)
    with pytest.raises(DatasetError, match=rf"episode file {bad} .*{message}"):
        EpisodeDataset(data, "all").verify()


def test_a_bad_episode_file_fails_the_run_before_step_1(tmp_path, capsys):
    from cdrl.data.store import EpisodeDataset

    data = _dataset(tmp_path / "data", n=8)
    bad = data / EpisodeDataset(data, "test")._entries[-1]["file"]  # a held-out file: training would reach it late
    _flip_frame_byte(bad)
    for command in (["train", "--run-dir", str(tmp_path / "run")], ["sweep", "--run-dir", str(tmp_path / "sweep")]):
        capsys.readouterr()
        assert cli_main([*command, "--data", str(data), "--preset", "tiny", "--unroll", "4", "--batch", "2",
                         "--steps", "3"]) == 2
        assert f"episode file {bad} is truncated or corrupt" in capsys.readouterr().err
    assert not (tmp_path / "run" / "config.json").exists() and not (tmp_path / "run" / "metrics.jsonl").exists()
    assert not (tmp_path / "sweep" / "sweep.json").exists()


def test_the_data_set_must_match_the_preset(tmp_path, capsys):
    data = _dataset(tmp_path / "data", size=8)
    assert cli_main(["train", "--run-dir", str(tmp_path / "run"), "--data", str(data), "--preset", "tiny"]) == 2
    assert f"data set {data} holds 8x8 frames; preset 'tiny' takes 16x16" in capsys.readouterr().err


# ---- SIGKILL during a sweep

SWEEP_GRID = ["--lr", "0.3", "1e4", "--seed", "0", "1"]  # lr 1e4 diverges within a few steps: it must stay stopped


def _progress_step(sweep: Path) -> int:
    try:
        return json.loads((sweep / "progress.json").read_text())["step"]
    except (FileNotFoundError, json.JSONDecodeError):
        return 0


@pytest.mark.e2e
def test_sigkill_during_a_sweep_resumes_every_configuration_exactly(tmp_path, capsys):
    straight = tmp_path / "straight"
    assert cli_main(["sweep", "--run-dir", str(straight), *TINY_RUN, *SWEEP_GRID, "--steps", "40",
                     "--checkpoint-every", "5"]) == 0
    expected = {r["name"]: r for r in json.loads((straight / "results.json").read_text())["rows"]}
    assert len(expected) == 4 and sum(r["diverged_at"] is not None for r in expected.values()) == 2

    killed = tmp_path / "killed"
    proc = _start("sweep", "--run-dir", str(killed), *TINY_RUN, *SWEEP_GRID, "--steps", "100000",
                  "--checkpoint-every", "5")
    _wait_for(proc, lambda: _progress_step(killed) >= 10, "two complete sweep checkpoints")
    _kill(proc)
    reached = _progress_step(killed)
    assert 10 <= reached < 40, reached
    before = {name: _records(killed / name / "metrics.jsonl")[:reached] for name in expected}
    capsys.readouterr()
    assert cli_main(["sweep", "--resume", str(killed), "--steps", "40"]) == 0
    rows = {r["name"]: r for r in json.loads((killed / "results.json").read_text())["rows"]}
    for name, row in expected.items():
        a, b = _records(straight / name / "metrics.jsonl"), _records(killed / name / "metrics.jsonl")
        assert [r["step"] for r in b] == [r["step"] for r in a]  # a diverged configuration stayed stopped
        assert max(abs(x["loss"] - y["loss"]) for x, y in zip(a, b)) <= 1e-6
        assert rows[name]["diverged_at"] == row["diverged_at"]
        assert rows[name]["test_bce"] == pytest.approx(row["test_bce"], rel=1e-5)
        # It went on from the checkpoint: the killed process's own records (frames/s, a
        # wall-clock measurement, included) are kept as they were.
        assert b[:reached] == before[name]


# ---- checkpoints: SIGKILL mid-write, a full disk, a torn metrics line

CKPT_RUN = [*TINY_RUN, "--checkpoint-every", "10"]


@pytest.fixture(scope="module")
def straight_run(tmp_path_factory) -> list[float]:
    """The per-step losses of an uninterrupted 30-step run."""
    run = tmp_path_factory.mktemp("straight") / "run"
    assert cli_main(["train", "--run-dir", str(run), *CKPT_RUN, "--steps", "30"]) == 0
    return [r["loss"] for r in _records(run / "metrics.jsonl")]


def _resume_matches(run: Path, straight: list[float], capsys) -> None:
    capsys.readouterr()
    assert cli_main(["train", "--resume", str(run), "--steps", "30"]) == 0, capsys.readouterr().err
    records = _records(run / "metrics.jsonl")
    assert [r["step"] for r in records] == list(range(30))
    assert max(abs(r["loss"] - x) for r, x in zip(records, straight)) <= 1e-6


# Kills its own process when orbax is about to rename checkpoint <step>'s finished temporary
# directory into place: the state and metadata are written, the checkpoint is not committed.
_KILL_AT_COMMIT = """
import os, signal, sys
from pathlib import Path
from orbax.checkpoint._src.path import async_path
rename = async_path.rename
async def killing_rename(src, dst):
    if Path(dst).name == sys.argv[1]:
        os.kill(os.getpid(), signal.SIGKILL)
    return await rename(src, dst)
async_path.rename = killing_rename
from cdrl.cli import main
sys.exit(main(sys.argv[2:]))
"""


def test_sigkill_during_a_checkpoint_write_restores_the_previous_one(tmp_path, straight_run, capsys):
    run = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-c", _KILL_AT_COMMIT, "20", "train", "--run-dir", str(run), *CKPT_RUN,
                           "--steps", "30"], capture_output=True, text=True)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert _finished_checkpoints(run / "checkpoints") == [10]
    assert [p.name for p in (run / "checkpoints").glob("20.orbax-checkpoint-tmp*")], "the kill missed the write"
    _resume_matches(run, straight_run, capsys)
    assert _finished_checkpoints(run / "checkpoints") == [10, 20, 30]


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # orbax's threads after the failure
def test_a_full_disk_during_a_checkpoint_fails_clearly_and_keeps_the_previous_one(tmp_path, straight_run, capsys,
                                                                                   monkeypatch):
    import errno

    from orbax.checkpoint._src.handlers import json_checkpoint_handler as handler

    real = handler.JsonCheckpointHandler._save_fn

    async def full_disk(self, item, directory):
        if "/20.orbax-checkpoint-tmp" in str(directory):
            (directory / "metadata").write_text('{"step": 2')
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return await real(self, item, directory)

    run = tmp_path / "run"
    monkeypatch.setattr(handler.JsonCheckpointHandler, "_save_fn", full_disk)
    capsys.readouterr()
    assert cli_main(["train", "--run-dir", str(run), *CKPT_RUN, "--steps", "30"]) == 2
    err = capsys.readouterr().err
    assert f"could not write checkpoint {run / 'checkpoints' / '20'}: No space left on device" in err
    assert "the earlier checkpoints are intact (steps: 10)" in err
    assert _finished_checkpoints(run / "checkpoints") == [10]
    monkeypatch.undo()
    _resume_matches(run, straight_run, capsys)


def test_a_torn_metrics_line_is_skipped_by_readers_and_repaired_by_resume(tmp_path, straight_run, capsys):
    run = tmp_path / "run"
    assert cli_main(["train", "--run-dir", str(run), *CKPT_RUN, "--steps", "20"]) == 0
    with open(run / "metrics.jsonl", "a") as f:
        f.write('{"step": 20, "loss": 0.4')  # a write cut off by a kill
    capsys.readouterr()
    assert cli_main(["eval", str(run)]) == 0
    assert cli_main(["plot", str(run), "--out", str(tmp_path / "plots")]) == 0
    _resume_matches(run, straight_run, capsys)


def _flip_a_bit(directory: Path) -> Path:
    """Flip one bit in the middle of the largest file under `directory`; returns the file."""
    largest = max((p for p in directory.rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)
    data = bytearray(largest.read_bytes())
    data[len(data) // 2] ^= 0x01
    largest.write_bytes(bytes(data))
    return largest


def test_a_flipped_bit_in_a_checkpoint_is_caught_by_train_eval_and_plot(tmp_path, straight_run, capsys):
    run = tmp_path / "run"
    assert cli_main(["train", "--run-dir", str(run), *CKPT_RUN, "--steps", "20"]) == 0
    flipped = _flip_a_bit(run / "checkpoints" / "20" / "state")
    name = flipped.relative_to(run / "checkpoints" / "20").as_posix()
    expected = (f"warning: checkpoint {run / 'checkpoints' / '20'} is corrupt: its file {name} does not match the "
                "checksum saved with it; restored the older checkpoint 10 instead")
    capsys.readouterr()
    assert cli_main(["eval", str(run)]) == 0
    out, err = capsys.readouterr()
    assert err.splitlines() == [expected] and json.loads(out.splitlines()[-1])[0]["steps"] == 10
    assert cli_main(["plot", str(run), "--out", str(tmp_path / "plots")]) == 0
    assert expected in capsys.readouterr().err.splitlines()
    _resume_matches(run, straight_run, capsys)  # from checkpoint 10: the losses of the uninterrupted run


def _as_written_before_checksums(checkpoint: Path) -> None:
    (checkpoint / "checksums.json").unlink()
    meta = checkpoint / "meta" / "metadata"
    meta.write_text(json.dumps({k: v for k, v in json.loads(meta.read_text()).items() if k != "checksums"}))


def test_a_checkpoint_without_its_checksums_and_an_unchecked_corrupt_one_fall_back_quietly(tmp_path):
    run = tmp_path / "run"
    assert cli_main(["train", "--run-dir", str(run), *CKPT_RUN, "--steps", "30"]) == 0
    ckpts = run / "checkpoints"
    (ckpts / "30" / "checksums.json").unlink()  # committed, but killed before its checksums: unfinished
    _as_written_before_checksums(ckpts / "20")  # a checkpoint of an older cdrl restores unchecked...
    (ckpts / "20" / "state" / "manifest.ocdbt").write_bytes(b"garbage")  # ...and this one fails inside orbax
    proc = subprocess.run(_cli("eval", str(run)), capture_output=True, text=True)  # orbax's stderr, unfiltered
    assert proc.returncode == 0, proc.stderr
    lines = proc.stderr.splitlines()
    assert lines[0] == (f"warning: checkpoint {ckpts / '30'} is unfinished: its save wrote no checksums; restored "
                        "the older checkpoint 10 instead")
    assert lines[1].startswith(f"warning: checkpoint {ckpts / '20'} is corrupt (ValueError: DATA_LOSS")
    assert lines[1].endswith("; restored the older checkpoint 10 instead") and len(lines) == 2  # no 'Event loop is closed'
    assert json.loads(proc.stdout.splitlines()[-1])[0]["steps"] == 10


class _Listed:
    """The part of `Checkpoints` a sweep's resume point reads: steps, and which fail their checksums."""

    def __init__(self, steps, corrupt=()):
        self._steps, self.corrupt = list(steps), set(corrupt)

    def steps(self):
        return self._steps

    def verify(self, step):
        from cdrl.runs.checkpoint import CorruptCheckpointError

        if step in self.corrupt:
            raise CorruptCheckpointError(f"checkpoint {step} is corrupt")
        return True


def test_a_sweep_resumes_from_the_newest_step_every_configuration_has_good(capsys):
    from cdrl.runs.checkpoint import CheckpointError
    from cdrl.runs.sweepstate import resume_point

    # Configuration 1 diverged at step 12 (its frozen state saved at 15), 0 and 2 reached 20.
    progress = {"step": 20, "alive": [True, False, True],
                "diverged": {1: {"diverged_at": 12, "diverged_group": "g", "diverged_ratio": 1e4, "finite": True}}}
    intact = [_Listed([15, 20]), _Listed([10, 15]), _Listed([15, 20])]
    assert resume_point(intact, progress, range(3)) is progress
    assert capsys.readouterr().err == ""
    # Checkpoint 20 of configuration 2 is corrupt: all go back to 15; 1 is still diverged there.
    back = resume_point([intact[0], intact[1], _Listed([15, 20], corrupt={20})], progress, range(3))
    assert back == {"step": 15, "alive": [True, False, True], "diverged": progress["diverged"]}
    assert capsys.readouterr().err == ("warning: checkpoint 20 is corrupt; the sweep resumes from step 15, where "
                                       "every configuration has a good checkpoint\n")
    # The frozen state of 1 is corrupt as well: back to 10, where 1 still trained (it diverges again at 12).
    older = [_Listed([10, 15, 20]), _Listed([10, 15], corrupt={15}), _Listed([10, 15, 20], corrupt={20})]
    assert resume_point(older, progress, range(3)) == {"step": 10, "alive": [True, True, True], "diverged": {}}
    with pytest.raises(CheckpointError, match="no step at which every configuration of the sweep has a good"):
        resume_point([_Listed([20], corrupt={20}), intact[1], intact[2]], progress, range(3))


# ---- data sets: SIGKILL during a collection, a full disk during an episode write

def _episode_files(out: Path) -> list[Path]:
    return sorted(out.glob("episode_*.npz"))


@pytest.mark.e2e
def test_sigkill_during_collect_keeps_whole_episodes_and_the_rerun_completes_the_set(tmp_path, capsys):
    import numpy as np

    from cdrl.data.store import EpisodeDataset, load_episode

    args = ["--episodes", "200", "--episode-steps", "30", "--obs-size", "16", "--seed", "3"]
    out = tmp_path / "killed"
    proc = _start("collect", str(out), *args)
    _wait_for(proc, lambda: len(_episode_files(out)) >= 20, "twenty finished episodes")
    _kill(proc)
    kept = _episode_files(out)
    assert 20 <= len(kept) < 200, len(kept)
    for path in kept:
        load_episode(path)  # whole episodes only; a .tmp- file may be left, never a torn episode
    assert not EpisodeDataset(out, "all").complete
    assert cli_main(["collect", str(out), *args]) == 0
    resumed = EpisodeDataset(out, "all")
    assert resumed.complete and len(resumed) == 200 and not list(out.glob(".tmp-*"))
    resumed.verify()
    straight = tmp_path / "straight"
    assert cli_main(["collect", str(straight), *args]) == 0
    assert json.loads((straight / "manifest.json").read_text()) == json.loads((out / "manifest.json").read_text())
    for i in (0, len(kept) - 1, len(kept), 199):  # before and after the kill
        a, b = load_episode(_episode_files(out)[i]), load_episode(_episode_files(straight)[i])
        assert np.array_equal(a.frames, b.frames) and np.array_equal(a.actions, b.actions)


def test_a_full_disk_during_an_episode_write_fails_clearly_and_keeps_the_episodes_before(tmp_path, capsys,
                                                                                         monkeypatch):
    import errno

    from cdrl.data import store

    real, calls = store._write_npz, []

    def full_disk(f, episode, compress):
        calls.append(1)
        if len(calls) == 20:
            f.write(b"PK\x03\x04 part of an episode")
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(f, episode, compress)

    args = ["--episodes", "24", "--episode-steps", "20", "--obs-size", "16"]
    out = tmp_path / "data"
    monkeypatch.setattr(store, "_write_npz", full_disk)
    capsys.readouterr()
    assert cli_main(["collect", str(out), *args]) == 2
    err = capsys.readouterr().err
    assert f"could not write episode file {out / 'episode_000019.npz'}: No space left on device" in err
    assert [p.name for p in _episode_files(out)] == [f"episode_{i:06d}.npz" for i in range(19)]
    assert not list(out.glob(".tmp-*"))
    listed = store.EpisodeDataset(out, "all")
    assert listed.indices == list(range(16))  # the manifest of the last whole batch
    listed.verify()
    monkeypatch.undo()
    assert cli_main(["collect", str(out), *args]) == 0
    assert store.EpisodeDataset(out, "all").complete


# ---- data that changed under a run, manifests pointing outside their data set, early checks

def _same_length_dataset(path: Path, n: int = 8) -> Path:
    from cdrl.data.writer import save_dataset

    episodes = _episodes(n)
    for i, e in enumerate(episodes):  # every episode 30 frames long: two files can be swapped unnoticed
        episodes[i] = type(e)(frames=e.frames[:30], actions=e.actions[:30], rewards=e.rewards[:30])
    save_dataset(path, episodes, test_fraction=0.25)
    return path


def test_a_data_set_that_changed_stops_the_resume_unless_allowed(tmp_path, capsys):
    from cdrl.data.store import EpisodeDataset

    data = _same_length_dataset(tmp_path / "data")
    run = tmp_path / "run"
    args = ["--data", str(data), "--preset", "tiny", "--unroll", "8", "--batch", "2", "--eval-every", "0",
            "--eval-episodes", "1", "--checkpoint-every", "5"]
    assert cli_main(["train", "--run-dir", str(run), *args, "--steps", "10"]) == 0
    first, second = (data / name for name in EpisodeDataset(data, "train").files[1:3])
    swapped = tmp_path / "swap"
    first.rename(swapped), second.rename(first), swapped.rename(second)
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    capsys.readouterr()
    assert cli_main(["train", "--resume", str(run), "--steps", "15"]) == 2
    err = capsys.readouterr().err
    assert (f"cdrl train: the data of run {run} changed since the run recorded it in {run / 'data.json'}: "
            f"{first.name} changed; {second.name} changed. Resuming would train on other episodes") in err
    assert "--allow-data-change" in err
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before  # nothing written
    assert cli_main(["train", "--resume", str(run), "--steps", "15", "--allow-data-change"]) == 0
    recorded = json.loads((run / "data.json").read_text())["changes"]
    assert recorded == [{"step": 10, "allowed": "--allow-data-change",
                         "changes": [f"{first.name} changed", f"{second.name} changed"]}]
    assert [r["step"] for r in _records(run / "metrics.jsonl")] == list(range(15))
    assert cli_main(["train", "--resume", str(run), "--steps", "16"]) == 0  # the changed data is the run's now


def _escape(data: Path, how: str) -> None:
    outside = data.parent / "outside.npz"
    outside.write_bytes((data / "episode_000001.npz").read_bytes())
    manifest = json.loads((data / "manifest.json").read_text())
    entry = manifest["episodes"][1]
    if how == "..":
        entry["file"] = "../outside.npz"
    elif how == "absolute":
        entry["file"] = str(outside)
    else:  # a symbolic link inside the directory that leads out of it
        (data / "link.npz").symlink_to(outside)
        entry["file"] = "link.npz"
    (data / "manifest.json").write_text(json.dumps(manifest))


@pytest.mark.parametrize("how", ["..", "absolute", "symlink"])
def test_a_manifest_cannot_point_outside_its_data_set(tmp_path, capsys, how):
    from cdrl.data.store import DatasetError, EpisodeDataset

    data = _dataset(tmp_path / "data")
    _escape(data, how)
    with pytest.raises(DatasetError, match=r"episode 1's file .* is outside the data set directory"):
        EpisodeDataset(data, "all")
    capsys.readouterr()
    assert cli_main(["train", "--run-dir", str(tmp_path / "run"), "--data", str(data), "--preset", "tiny"]) == 2
    assert "is outside the data set directory" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def _three_episodes(t: Path) -> Path:
    from cdrl.data.writer import save_dataset

    save_dataset(t / "data", _episodes(3), test_fraction=0.1)  # round(0.3) = 0 held-out episodes
    return t / "data"


def _one_frame_dataset(t: Path) -> Path:
    from cdrl.data.writer import save_dataset

    episodes = _episodes(8)
    episodes[5] = type(episodes[5])(frames=episodes[5].frames[:1], actions=episodes[5].actions[:1],
                                    rewards=episodes[5].rewards[:1])
    save_dataset(t / "data", episodes, test_fraction=0.25)
    return t / "data"


EARLY = {
    "an empty held-out split": (lambda t: ["--data", str(_three_episodes(t))],
                                "data set {t}/data holds no held-out episodes (its test split is empty: 3 episodes"),
    "no held-out episodes to evaluate": (lambda t: ["--data", "synthetic", "--eval-episodes", "0"],
                                         "eval_episodes must be >= 1, got 0"),
    "a one-frame episode": (lambda t: ["--data", str(_one_frame_dataset(t))],
                            "episode file {t}/data/episode_000005.npz of data set {t}/data has 1 frame(s); at least 2 "
                            "are needed"),
    "lr nan": (lambda t: ["--data", "synthetic", "--lr", "nan"], "lr must be a finite number, got nan"),
    "lr inf": (lambda t: ["--data", "synthetic", "--lr", "inf"], "lr must be a finite number, got inf"),
    "a negative evaluation interval": (lambda t: ["--data", "synthetic", "--eval-every", "-5"],
                                       "eval_every must be >= 0, got -5"),
    "game parameters for synthetic data": (lambda t: ["--data", "synthetic", "--env", "max_steps=300"],
                                           "env 'max_steps=300' sets the built-in game, which a run on data "
                                           "'synthetic' never plays"),
}


@pytest.mark.parametrize("command", ["train", "sweep"])
@pytest.mark.parametrize("case", EARLY)
def test_early_checks_fail_before_anything_is_written(tmp_path, capsys, case, command):
    args, message = EARLY[case]
    argv = [command, "--run-dir", str(tmp_path / "runs" / "new"), "--preset", "tiny", "--unroll", "4",
            "--batch", "1", "--steps", "3", *args(tmp_path)]
    (tmp_path / "empty").mkdir()
    capsys.readouterr()
    assert cli_main(argv) == 2
    assert f"cdrl {command}: " + message.format(t=tmp_path) in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()  # not even a lone .lock in a directory made for it
    argv[2] = str(tmp_path / "empty")  # a directory that was there before stays, without a .lock
    assert cli_main(argv) == 2 and list((tmp_path / "empty").iterdir()) == []


# ---- bad input: each refused with a named error

def _fake_sweep(root: Path) -> Path:
    import dataclasses

    from cdrl.runs.config import RunConfig

    sweep = root / "sweep"
    sweep.mkdir()
    (sweep / "sweep.json").write_text(json.dumps({"base": dataclasses.asdict(RunConfig()), "grid": {}}))
    return sweep


BAD_CLI = {
    "unknown variant": (lambda t: ["train", "--variant", "nope"], "unknown variant 'nope'"),
    "unknown preset": (lambda t: ["train", "--preset", "huge"], "unknown architecture preset 'huge'"),
    "zero unroll": (lambda t: ["train", "--unroll", "0"], "unroll must be >= 1, got 0"),
    "negative lr": (lambda t: ["train", "--lr", "-1"], "lr must be > 0, got -1.0"),
    "unknown optimiser": (lambda t: ["train", "--optimizer", "adagrad"], "optimizer must be one of sgd"),
    "unknown level": (lambda t: ["train", "--level", "lava"], "level must be one of thesis"),
    "bad game parameter": (lambda t: ["train", "--env", "gravity=1"], "bad game parameter 'gravity=1'"),
    "resume of nothing": (lambda t: ["train", "--resume", str(t / "nowhere")],
                          "cannot resume: {t}/nowhere/config.json does not exist"),
    "data set without a manifest": (lambda t: ["train", "--data", str(t)], "{t} has no manifest.json"),
    "sweep of a controller": (lambda t: ["sweep", "--variant", "final_proposal", "--preset", "tiny"],
                              "'thesis_ascent' is not covered by online sweeps yet"),
    "sweep resume of nothing": (lambda t: ["sweep", "--resume", str(t / "nowhere")],
                                "sweep directory {t}/nowhere does not exist"),
    "sweep resume of a non-sweep": (lambda t: ["sweep", "--resume", str(t)], "{t} is not a sweep directory"),
    "sweep resume changing the grid": (lambda t: ["sweep", "--resume", str(_fake_sweep(t)), "--lr", "0.5"],
                                       "--lr cannot change (only checkpoint_every, devices, eval_episodes"),
    "eval of nothing": (lambda t: ["eval", str(t / "nowhere")], "run directory {t}/nowhere does not exist"),
    "collect over another data set": (lambda t: ["collect", str(_dataset(t / "data"))],
                                      "was written by a different collection"),
    "unknown gymnasium game": (lambda t: ["collect", str(t / "g"), "--env", "NoSuchGame-v0"],
                               "unknown gymnasium environment 'NoSuchGame-v0'"),
    "a game whose observations are not images": (
        lambda t: ["collect", str(t / "g"), "--env", "CartPole-v1"],
        "CartPole-v1's observations are not images (observation space Box("),
    "malformed --env-kwargs": (lambda t: ["collect", str(t / "g"), "--env", "CartPole-v1", "--obs", "render",
                                          "--env-kwargs", "gravity"], "bad --env-kwargs item 'gravity'"),
    "--env-kwargs the game does not take": (
        lambda t: ["collect", str(t / "g"), "--env", "CartPole-v1", "--obs", "render", "--env-kwargs", "bogus=1"],
        "gymnasium environment 'CartPole-v1' does not take --env-kwargs"),
    "the built-in game's policy for a gymnasium game": (
        lambda t: ["collect", str(t / "g"), "--env", "CartPole-v1", "--obs", "render", "--policy", "behaviour"],
        "policy 'behaviour' is for the built-in game"),
    "a crop outside the frame": (
        lambda t: ["collect", str(t / "g"), "--env", "CartPole-v1", "--obs", "render", "--crop", "0", "0", "500", "500"],
        "--crop [0, 0, 500, 500] does not fit in the 400x600 frames"),
    "a crop without a gymnasium game": (lambda t: ["collect", str(t / "g"), "--crop", "0", "0", "64", "64"],
                                        "--crop is for a gymnasium game (--env ID)"),
}


@pytest.mark.parametrize("case", BAD_CLI)
def test_bad_cli_input_is_refused_by_name(tmp_path, capsys, case):
    args, message = BAD_CLI[case]
    argv = args(tmp_path)
    if argv[0] in ("train", "sweep") and "--resume" not in argv:
        argv += ["--run-dir", str(tmp_path / "run"), "--preset", "tiny"] if "--preset" not in argv else [
            "--run-dir", str(tmp_path / "run")]
    capsys.readouterr()
    assert cli_main(argv) == 2
    assert message.format(t=tmp_path) in capsys.readouterr().err


def _bad_api(case: str, tmp: Path):
    import numpy as np

    from cdrl.data.episode import Episode
    from cdrl.data.store import EpisodeDataset
    from cdrl.data.stream import ChunkStream
    from cdrl.runs.config import RunConfig
    from cdrl.runs.sweep import Grid
    from envs.preprocess import preprocess

    return {
        "grid repeats a value": lambda: Grid(lr=(0.1, 0.1)),
        "empty episode source": lambda: ChunkStream([], batch=1, unroll=4),
        "frames without a time axis": lambda: Episode(frames=np.zeros((3, 4), np.uint8),
                                                      actions=np.zeros((3, 3), np.float32),
                                                      rewards=np.zeros(3, np.float32)),
        "unknown split": lambda: EpisodeDataset(_dataset(tmp / "d"), split="valid"),
        "crop not a multiple of the output": lambda: preprocess(np.zeros((10, 10, 3), np.uint8), None, (3, 3)),
        "zero checkpoint interval": lambda: RunConfig(checkpoint_every=0),
    }[case]


BAD_API = {
    "grid repeats a value": "the grid repeats a value of lr",
    "empty episode source": "the episode source is empty",
    "frames without a time axis": r"Episode.frames must be \[N, H, W\], got shape \(3, 4\)",
    "unknown split": "split must be 'train', 'test' or 'all', got 'valid'",
    "crop not a multiple of the output": r"crop size \(10, 10\) is not a multiple of out_size \(3, 3\)",
    "zero checkpoint interval": "checkpoint_every must be >= 1, got 0",
}


@pytest.mark.parametrize("case", BAD_API)
def test_bad_api_input_is_refused_by_name(tmp_path, case):
    with pytest.raises(ValueError, match=BAD_API[case]):
        _bad_api(case, tmp_path)()


class _Events(Job):
    """A job that only logs what the host loop asks of it."""

    desc, ratio_names = "events", ["g"]

    def __init__(self):
        self.events = []

    def step(self, state):
        return state + 1, {"loss": 0.0, "terms": {}, "max_ratio": 0.0, "worst_group": 0, "ratios": [0.0],
                           "finite": True, "diverged": False}

    def evaluate(self, step, state, lanes):
        self.events.append(("eval", step))
        return {0: ({"step": step}, None)}

    def save(self, step, state, saves, alive, diverged):
        self.events.append(("save", step))


def test_the_final_evaluation_is_recorded_before_the_final_checkpoint():
    """A run killed after its last checkpoint has its final evaluation: the loop evaluates the
    last step before checkpointing it (a kill between the two resumes from the checkpoint
    before, which evaluates again), and a run resumed at its last step evaluates nothing."""
    job = _Events()
    host_loop(job, 0, Plan(steps=4, eval_every=2, checkpoint_every=2), [Sink()])
    assert job.events == [("eval", 2), ("save", 2), ("eval", 4), ("save", 4)]
    finished = _Events()
    host_loop(finished, 4, Plan(steps=4, start=4, eval_every=2, checkpoint_every=2), [Sink()])
    assert finished.events == []


def test_only_asyncio_reports_of_unawaited_reads_are_dropped_and_only_after_a_failed_read(caplog):
    import asyncio

    from cdrl.runs.checkpoint import _ClosedLoopCallbacks

    def report(message):  # as asyncio reports them: the message, then the future on the next line
        loop = asyncio.new_event_loop()
        future = loop.create_future()
        future.set_exception(ValueError("DATA_LOSS"))
        future.exception()
        loop.call_exception_handler({"message": message, "exception": ValueError("DATA_LOSS"), "future": future})
        loop.close()

    callbacks, asyncio_log, hook = _ClosedLoopCallbacks(), logging.getLogger("asyncio"), sys.unraisablehook
    filters = list(asyncio_log.filters)
    try:
        with caplog.at_level("ERROR", logger="asyncio"):
            with callbacks.dropped():
                report("Task exception was never retrieved")
                report("Future exception was never retrieved")
                report("Exception in callback")
            report("Task exception was never retrieved")  # no read failed: the filter is gone with the block
            assert asyncio_log.filters == filters and sys.unraisablehook is hook
            with callbacks.dropped() as inside:
                inside.keep()
            report("Future exception was never retrieved")  # a read failed: its futures may be collected later
            report("Exception in callback")
        assert [r.getMessage().partition("\n")[0] for r in caplog.records] == [
            "Exception in callback", "Task exception was never retrieved", "Exception in callback"]
    finally:
        asyncio_log.filters[:] = filters
        sys.unraisablehook = hook


def test_the_data_set_must_match_the_presets_max_filter(tmp_path, capsys):
    """Game data shrunk without a max filter is refused by a run with a 5 x 5 one (here by the
    old preset name small-max) before anything is written, the message naming both filters and
    the fix."""
    from cdrl.data.collect import collect

    data = tmp_path / "data"
    collect(data, 2, policy="uniform", max_steps=6, batch_size=2, chunk_steps=4, progress=False, obs_size=64)
    run = tmp_path / "run"
    assert cli_main(["train", "--run-dir", str(run), "--data", str(data), "--preset", "small-max",
                     "--steps", "1"]) == 2
    err = capsys.readouterr().err
    assert (f"data set {data} was shrunk after a max filter of side 1; this run sees the game after one "
            "of side 5 (--max-filter) (collect it with --max-filter 5" in err)
    assert not (run / "config.json").exists()
