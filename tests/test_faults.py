"""Fault injection: what a run, a sweep and a data set survive (the README's table).

One writer per directory (a second is refused with the holder's pid; a killed holder's lock
never blocks; readers work meanwhile), SIGKILL during a collection, a sweep and a checkpoint
write, a full disk during a checkpoint or an episode write, a torn metrics line, and bad
input to the CLI and the API. Kill tests wait for a finished checkpoint (or episode) before
killing, so they cannot pass without the fault having happened.
"""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cdrl.cli import main as cli_main
from cdrl.data.lock import LOCK_NAME, DirLock, LockedError

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
    """Steps of the checkpoints orbax has finished (it renames '<step>.orbax-checkpoint-tmp-*'
    to '<step>' when one is complete)."""
    if not ckpt_dir.exists():
        return []
    return sorted(int(p.name) for p in ckpt_dir.iterdir() if p.name.isdigit())


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
    from cdrl.data import store

    out = tmp_path / "data"
    proc = _start("collect", str(out), "--episodes", "400", "--episode-steps", "30", "--obs-size", "16")
    _wait_for(proc, lambda: (out / LOCK_NAME).exists() and (out / LOCK_NAME).read_text().strip() == str(proc.pid),
              "the collection's lock")
    with pytest.raises(LockedError, match=rf"data set {out} is in use by pid {proc.pid}"):
        store.collect(out, 400, max_steps=30, obs_size=16)
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
    from cdrl.data.store import save_dataset

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
