"""Beyond one device: sweeps sharded over a mesh's config axis, data-parallel runs, and both
over two processes joined by `jax.distributed` on localhost (CPU collectives through gloo).

Two host devices in one process need `--xla_force_host_platform_device_count` before JAX
starts, so those checks run in a subprocess; the two-process checks start two `cdrl`
processes (`--distributed`, coordinator on a free localhost port) and compare what they write
with what one process on one device writes.
"""
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from cdrl.cli import main as cli_main
from cdrl.models import make_variant
from cdrl.runs.config import upgrade
from cdrl.runs.checkpoint import Checkpoints
from cdrl.runs.rundir import RunDir
from cdrl.training.step import init_state

pytestmark = pytest.mark.e2e

TINY = ["--data", "synthetic", "--preset", "tiny", "--episodes", "6", "--episode-steps", "30", "--unroll", "8",
        "--batch", "2", "--eval-episodes", "1"]
SWEEP_GRID = ["--lr", "0.3", "0.1", "1e4"]  # three configurations on two devices: one pad; lr 1e4 diverges
TIMEOUT = 300


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _flags_without_device_count() -> str:
    """This session's XLA flags (tests/conftest.py) less any host device count."""
    flags = os.environ.get("XLA_FLAGS", "").split()
    return " ".join(f for f in flags if not f.startswith("--xla_force_host_platform_device_count"))


def _start(count: int, *args: str) -> list[subprocess.Popen]:
    """`count` processes of `cdrl ARGS --distributed`, joined on a localhost coordinator."""
    port = _free_port()
    procs = []
    for i in range(count):
        env = {**os.environ, "XLA_FLAGS": _flags_without_device_count()}
        env.update(JAX_PLATFORMS="cpu", JAX_COORDINATOR_ADDRESS=f"localhost:{port}", JAX_NUM_PROCESSES=str(count),
                   JAX_PROCESS_ID=str(i))
        procs.append(subprocess.Popen([sys.executable, "-m", "cdrl.cli", *args, "--distributed"], env=env,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True))
    return procs


def _finish(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        try:
            _, err = p.communicate(timeout=TIMEOUT)
        except subprocess.TimeoutExpired:
            for q in procs:
                q.kill()
            pytest.fail("a distributed process timed out")
        assert p.returncode == 0, err[-3000:]


def _kill_when(procs: list[subprocess.Popen], ready, what: str) -> None:
    """SIGKILL every process once `ready()` holds (fail if one ends first)."""
    deadline = time.time() + TIMEOUT
    while not ready():
        ended = [p for p in procs if p.poll() is not None]
        if ended or time.time() > deadline:
            for p in procs:
                p.kill()
            pytest.fail(f"no {what}: {ended[0].stderr.read()[-3000:] if ended else 'timed out'}")
        time.sleep(0.05)
    for p in procs:
        os.kill(p.pid, signal.SIGKILL)
        p.wait()
        p.stderr.close()


def _records(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def _losses(run: Path) -> list[float]:
    return [r["loss"] for r in _records(run / "metrics.jsonl")]


def _progress(sweep: Path) -> int:
    try:
        return json.loads((sweep / "progress.json").read_text())["step"]
    except (FileNotFoundError, json.JSONDecodeError):
        return 0


def _files(run_dir: Path) -> set[str]:
    """A run directory's files, without what is named at random or by its writer: TensorBoard
    event files and orbax's array storage (`checkpoints/<step>/state/`, one part per process)."""
    return {str(p.relative_to(run_dir)) for p in run_dir.rglob("*") if p.is_file()
            and "tfevents" not in p.name and "state" not in p.relative_to(run_dir).parts}


def _checkpoint(run: Path, step: int):
    """(state, metadata) of a run's checkpoint `step`, restored on this process's one device."""
    cfg = RunDir(run).read_config()
    variant = make_variant(cfg.variant, cfg.arch)
    like = jax.eval_shape(lambda: init_state(variant, jax.random.PRNGKey(0), cfg.batch, cfg.hparams(variant)))
    return Checkpoints(run / "checkpoints").restore(step, like)


def _same_checkpoints(run: Path, reference: Path, rtol: float) -> None:
    """The same checkpoint steps; at each, the same metadata and the state within `rtol`."""
    steps = Checkpoints(run / "checkpoints").steps()
    assert steps and steps == Checkpoints(reference / "checkpoints").steps()
    for step in steps:
        (state, meta), (expected, expected_meta) = _checkpoint(run, step), _checkpoint(reference, step)
        assert {k: v for k, v in meta.items() if k != "config"} == {k: v for k, v in expected_meta.items() if k != "config"}
        for x, y in zip(jax.tree.leaves(state), jax.tree.leaves(expected), strict=True):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=rtol)


# ---- two devices in one process

TWO_DEVICES = r'''
import json, sys
from pathlib import Path
import jax, numpy as np
assert jax.device_count() == 2, jax.devices()
from cdrl.data.stream import ChunkStream
from cdrl.data.synthetic import synthetic_episodes
from cdrl.models import make_variant
from cdrl.models.arch import TINY
from cdrl.runs.config import RunConfig
from cdrl.runs.sweep import Grid, sweep_run
from cdrl.training.optim import HParams
from cdrl.training.parallel import DataParallel
from cdrl.training.step import init_state, train_step

out = Path(sys.argv[1])
result = {}
base = dict(preset="tiny", data="synthetic", episodes=6, episode_steps=30, unroll=8, batch=2, steps=6,
            eval_every=3, eval_episodes=1, checkpoint_every=3, tensorboard=False)
for devices in (1, 2):
    rows = sweep_run(RunConfig(variant="main", devices=devices, **base), Grid(lr=(0.3, 0.1, 1e4)),
                     out / f"sweep{devices}", progress=False)
    result[f"sweep{devices}"] = {r["name"]: {"test_bce": r["test_bce"], "diverged_at": r["diverged_at"],
        "losses": [json.loads(l)["loss"] for l in (out / f"sweep{devices}" / r["name"] / "metrics.jsonl").read_text().splitlines()]}
        for r in rows}
    rows = sweep_run(RunConfig(variant="baseline_recurrent", devices=devices, **base), Grid(seed=(0, 1)),
                     out / f"staged{devices}", progress=False)
    result[f"staged{devices}"] = {r["name"]: r["test_bce"] for r in rows}

# the data-parallel step against the one-device step, from the same state on the same chunks
variant = make_variant("main_action", TINY)
hp = HParams.create(variant, lr=0.1, momentum=0.9)
stream = ChunkStream(synthetic_episodes(8, 30, 16, pushed=True), batch=4, unroll=8)
chunks = [stream.next_chunk() for _ in range(3)]
one = init_state(variant, jax.random.PRNGKey(0), 4, hp)
parallel = DataParallel.create(2, 4)
two = parallel.place_state(init_state(variant, jax.random.PRNGKey(0), 4, hp))
step = parallel.step(variant, two)
result["dp"] = []
for chunk in chunks:
    one, m1 = train_step(variant, one, hp, chunk)
    two, m2 = step(two, parallel.place(hp), parallel.place_chunk(chunk))
    result["dp"].append({"loss": [float(m1["loss"]), float(m2["loss"])],
                         "param_diff": max(float(np.max(np.abs(np.asarray(a) - np.asarray(b))))
                                           for a, b in zip(jax.tree.leaves(one.params), jax.tree.leaves(two.params))),
                         "carry_sharded": [str(x.sharding.spec) for x in jax.tree.leaves(two.carry)],
                         "params_replicated": all(x.sharding.is_fully_replicated for x in jax.tree.leaves(two.params))})
# the built-in game's collection with its games over the two devices
from cdrl.data.collect import _rollout_fn, collect, games_sharding
from envs.slither import canonical_params
for devices in (1, 2):
    collect(out / f"collect{devices}", 4, policy="uniform", seed=3, max_steps=12, batch_size=4, chunk_steps=8,
            progress=False, compress=False, devices=devices)
result["collect"] = {d: {p.name: p.read_bytes().hex() for p in sorted((out / f"collect{d}").glob("episode_*"))}
                     for d in (1, 2)}
start, _ = _rollout_fn((), "uniform", 8)
carry = start(jax.device_put(jax.random.split(jax.random.PRNGKey(0), 4), games_sharding(2, 4)),
              canonical_params())
result["collect_sharded"] = sorted({len(x.sharding.device_set) for x in jax.tree.leaves(carry)})
errors = {}
for name, make in {"batch": lambda: DataParallel.create(2, 3), "devices": lambda: DataParallel.create(4, 4),
                   "games_batch": lambda: games_sharding(2, 3), "games_devices": lambda: games_sharding(3, 3)}.items():
    try:
        make()
    except ValueError as exc:
        errors[name] = str(exc)
result["errors"] = errors
print("RESULT " + json.dumps(result))
'''


def test_sharded_sweep_and_data_parallel_step_equal_one_device(tmp_path):
    """Two host devices: a sweep whose config axis is sharded over them (three configurations,
    padded to four; one diverges; a two-stage variant too) trains exactly what the vmapped
    one-device sweep trains, the data-parallel step (B split over the devices, gradients
    all-reduced) equals the one-device step, and the game's collection with its games split
    over them writes the one-device data set byte for byte."""
    env = {**os.environ, "XLA_FLAGS": f"{_flags_without_device_count()} --xla_force_host_platform_device_count=2",
           "JAX_PLATFORMS": "cpu"}
    proc = subprocess.run([sys.executable, "-c", TWO_DEVICES, str(tmp_path)], env=env, capture_output=True,
                          text=True, timeout=TIMEOUT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(next(line for line in proc.stdout.splitlines() if line.startswith("RESULT "))[7:])
    one, two = result["sweep1"], result["sweep2"]
    assert sorted(one) == sorted(two) and len(one) == 3
    for name in one:
        assert len(two[name]["losses"]) == len(one[name]["losses"])  # the diverged one stopped at the same step
        np.testing.assert_allclose(two[name]["losses"], one[name]["losses"], rtol=1e-6, atol=1e-7)
        assert two[name]["diverged_at"] == one[name]["diverged_at"]
        assert two[name]["test_bce"] == pytest.approx(one[name]["test_bce"], rel=1e-6)
    assert sum(r["diverged_at"] is not None for r in one.values()) == 1
    assert result["staged2"] == pytest.approx(result["staged1"], rel=1e-6)
    for record in result["dp"]:
        assert record["loss"][1] == pytest.approx(record["loss"][0], rel=1e-5)
        assert record["param_diff"] < 1e-5
        assert record["params_replicated"] and set(record["carry_sharded"]) == {"P('data',)"}
    assert result["dp"][0]["loss"] != result["dp"][-1]["loss"]  # it trained
    assert "batch 3 does not split over 2 devices" in result["errors"]["batch"]
    assert "devices=4, but only 2 cpu device(s)" in result["errors"]["devices"]
    # the game's collection: each episode's file the same bytes with its games on two devices
    assert len(result["collect"]["1"]) == 4 and result["collect"]["2"] == result["collect"]["1"]
    assert result["collect_sharded"] == [2]
    assert "--batch-size 3 does not split over 2 devices" in result["errors"]["games_batch"]
    assert "--devices 3: this process has 2 cpu device(s)" in result["errors"]["games_devices"]


# ---- two processes


def test_two_process_sweep_killed_and_resumed_writes_what_one_process_writes(tmp_path):
    """Two processes (one device each) train a sweep as one program; killed (both, SIGKILL)
    after two complete checkpoints and resumed, they have written the same run directories as
    one process on one device: the same files, per-step losses, evaluations, results and
    checkpoints (state and data cursor). Each configuration's directory is held by the process
    that trains it (its lock names that process), the sweep directory by process 0."""
    one, two = tmp_path / "one", tmp_path / "two"
    args = [*TINY, *SWEEP_GRID, "--eval-every", "4", "--checkpoint-every", "4"]
    assert cli_main(["sweep", "--run-dir", str(one), *args, "--steps", "24"]) == 0
    _kill_when(_start(2, "sweep", "--run-dir", str(two), *args, "--steps", "100000"),
               lambda: _progress(two) >= 8, "two complete sweep checkpoints")
    killed_at = _progress(two)
    assert 8 <= killed_at < 24, killed_at
    resumed = _start(2, "sweep", "--resume", str(two), "--steps", "24")
    _finish(resumed)

    expected = {r["name"]: r for r in json.loads((one / "results.json").read_text())["rows"]}
    rows = {r["name"]: r for r in json.loads((two / "results.json").read_text())["rows"]}
    assert list(rows) == list(expected) and sum(r["diverged_at"] is not None for r in rows.values()) == 1
    assert _files(two) == _files(one)
    for index, (name, row) in enumerate(expected.items()):
        a, b = _records(one / name / "metrics.jsonl"), _records(two / name / "metrics.jsonl")
        assert [r["step"] for r in b] == [r["step"] for r in a]  # the diverged one stopped at the same step
        assert max(abs(x["loss"] - y["loss"]) for x, y in zip(a, b)) <= 1e-6
        evals = _records(one / name / "eval.jsonl"), _records(two / name / "eval.jsonl")
        assert [r["step"] for r in evals[1]] == [r["step"] for r in evals[0]]
        np.testing.assert_allclose([r["bce"] for r in evals[1]], [r["bce"] for r in evals[0]], rtol=1e-6)
        assert rows[name]["diverged_at"] == row["diverged_at"]
        assert rows[name]["test_bce"] == pytest.approx(row["test_bce"], rel=1e-6)
        assert (two / name / "config.json").read_text() == (one / name / "config.json").read_text()
        # Two compiled programs (one configuration per device against two vmapped on one)
        # sum in different orders: after 24 steps single parameters differ by about 1e-6.
        _same_checkpoints(two / name, one / name, rtol=1e-5)
        # configurations 0 and 1 are on process 0's device, 2 (and the pad) on process 1's
        assert int((two / name / ".lock").read_text()) == resumed[0 if index < 2 else 1].pid
    assert int((two / ".lock").read_text()) == resumed[0].pid


def test_two_process_data_parallel_run_equals_one_device_and_resumes_exactly(tmp_path):
    """`cdrl train --distributed`: two processes split the B streams; the per-step losses and
    the checkpointed states equal one device's within float tolerance (the gradient is
    all-reduced). The same run killed (both processes) after two checkpoints and resumed
    continues exactly: its losses equal the uninterrupted two-process run's."""
    args = [*TINY[:-4], "--batch", "4", "--eval-episodes", "1", "--eval-every", "4", "--checkpoint-every", "4"]
    one, straight, killed = tmp_path / "one", tmp_path / "straight", tmp_path / "killed"
    assert cli_main(["train", "--run-dir", str(one), *args, "--steps", "24"]) == 0
    _finish(_start(2, "train", "--run-dir", str(straight), *args, "--steps", "24"))
    _kill_when(_start(2, "train", "--run-dir", str(killed), *args, "--steps", "100000"),
               lambda: len(Checkpoints(killed / "checkpoints").steps()) >= 2, "two complete checkpoints")
    assert Checkpoints(killed / "checkpoints").steps()[-1] < 24
    _finish(_start(2, "train", "--resume", str(killed), "--steps", "24"))

    np.testing.assert_allclose(_losses(straight), _losses(one), rtol=1e-5)
    _same_checkpoints(straight, one, rtol=1e-5)
    assert upgrade(json.loads((straight / "config.json").read_text()))["devices"] == 0  # every device of every process
    assert max(abs(x - y) for x, y in zip(_losses(killed), _losses(straight), strict=True)) <= 1e-6
    _same_checkpoints(killed, straight, rtol=1e-6)
    assert [r["step"] for r in _records(killed / "eval.jsonl")] == [r["step"] for r in _records(straight / "eval.jsonl")]


def test_distributed_and_devices_refuse_bad_settings(tmp_path, capsys, monkeypatch):
    """Named errors: a partial --distributed environment, more devices than there are, a
    controller variant spread over devices."""
    monkeypatch.setenv("JAX_NUM_PROCESSES", "2")
    monkeypatch.delenv("JAX_COORDINATOR_ADDRESS", raising=False)
    monkeypatch.delenv("JAX_PROCESS_ID", raising=False)
    assert cli_main(["sweep", "--run-dir", str(tmp_path / "s"), "--distributed", *TINY]) == 2
    assert "--distributed: JAX_COORDINATOR_ADDRESS, JAX_PROCESS_ID unset" in capsys.readouterr().err
    assert cli_main(["train", "--run-dir", str(tmp_path / "t"), *TINY, "--devices", "3", "--steps", "1"]) == 2
    assert "devices=3, but only 1 cpu device(s) are available over 1 process(es)" in capsys.readouterr().err
    assert cli_main(["train", "--run-dir", str(tmp_path / "c"), "--variant", "final_proposal", "--preset", "tiny",
                     "--devices", "2"]) == 2
    assert "devices=2: learners that play the game train on one device" in capsys.readouterr().err
