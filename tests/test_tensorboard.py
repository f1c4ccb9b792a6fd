"""TensorBoard event files of `cdrl train` and `cdrl sweep`: read back with tensorboardX's
protocol buffers, every scalar equals its metrics.jsonl / eval.jsonl number, and the
predicted frames are there as images at each evaluation."""
import json
import struct
from pathlib import Path

import pytest
from tensorboardX.proto import event_pb2

from cdrl.cli import main as cli_main
from cdrl.runs.config import upgrade

RUN = ["--data", "synthetic", "--preset", "tiny", "--episodes", "6", "--episode-steps", "30", "--unroll", "8",
       "--batch", "2", "--lr", "0.3", "--eval-episodes", "1", "--checkpoint-every", "6", "--eval-every", "6"]


def read_events(tb_dir: Path) -> tuple[dict[str, dict[int, float]], dict[str, dict[int, tuple[int, int]]]]:
    """(tag -> step -> scalar, tag -> step -> (height, width) of the image) of every event file
    in `tb_dir`, oldest file first; a file's 'purge from step s' marker (what a resumed run
    writes) drops the earlier files' events at and after s, as TensorBoard does."""
    scalars: dict[str, dict[int, float]] = {}
    images: dict[str, dict[int, tuple[int, int]]] = {}
    files = sorted(tb_dir.glob("events.out.tfevents.*"), key=lambda p: p.stat().st_mtime_ns)
    assert files, f"no event file in {tb_dir}"
    for path in files:
        data, pos = path.read_bytes(), 0
        while pos < len(data):
            (length,) = struct.unpack("<Q", data[pos:pos + 8])
            event = event_pb2.Event.FromString(data[pos + 12:pos + 12 + length])
            pos += 12 + length + 4
            if event.HasField("session_log") and event.session_log.status == event_pb2.SessionLog.START:
                for table in (*scalars.values(), *images.values()):
                    for step in [s for s in table if s >= event.step]:
                        del table[step]
            for value in event.summary.value:
                if value.HasField("image"):
                    images.setdefault(value.tag, {})[event.step] = (value.image.height, value.image.width)
                else:
                    scalars.setdefault(value.tag, {})[event.step] = value.simple_value
    return scalars, images


def _lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def check_against_logs(run: Path, steps: int, evals: list[int]) -> None:
    scalars, images = read_events(run / "tb")
    records = _lines(run / "metrics.jsonl")
    assert [r["step"] for r in records] == list(range(steps))
    for r in records:
        expected = {"loss": r["loss"], "max_ratio": r["max_ratio"], "fps": r["fps"],
                    **{f"terms/{k}": v for k, v in r["terms"].items()},
                    **{f"ratio/{k}": v for k, v in r["ratios"].items()}}
        for tag, value in expected.items():
            assert scalars[tag][r["step"]] == pytest.approx(value, rel=1e-6), (tag, r["step"])
    assert set(scalars["loss"]) == set(range(steps))
    assert len([t for t in scalars if t.startswith("ratio/")]) == len(records[0]["ratios"]) > 5
    held_out = _lines(run / "eval.jsonl")
    assert [e["step"] for e in held_out] == evals
    for e in held_out:
        for name in ("bce", "copy_bce", "target_entropy", "excess_ratio"):
            assert scalars[f"eval/{name}"][e["step"]] == pytest.approx(e[name], rel=1e-6)
    assert set(images["predictions"]) == set(evals)
    assert images["predictions"][evals[0]] == (2 * 16, 8 * 16)  # 8 targets above 8 predictions, 16 x 16 each


def test_train_writes_tensorboard_events_equal_to_its_logs(tmp_path):
    run = tmp_path / "run"
    assert cli_main(["train", "--run-dir", str(run), *RUN, "--steps", "6"]) == 0
    assert cli_main(["train", "--resume", str(run), "--steps", "12"]) == 0  # a second event file, from step 6
    assert len(list((run / "tb").glob("events.out.tfevents.*"))) == 2
    check_against_logs(run, 12, [6, 12])


def test_sweep_writes_tensorboard_events_per_configuration(tmp_path):
    sweep = tmp_path / "sweep"
    assert cli_main(["sweep", "--run-dir", str(sweep), *RUN, "--lr", "0.3", "0.1", "--steps", "12"]) == 0
    for config in ("lr0.3-mom0.9-seed0-thr1000", "lr0.1-mom0.9-seed0-thr1000"):
        check_against_logs(sweep / config, 12, [6, 12])


def test_tensorboard_can_be_switched_off(tmp_path):
    run = tmp_path / "run"
    assert cli_main(["train", "--run-dir", str(run), *RUN, "--steps", "2", "--no-tensorboard"]) == 0
    assert (run / "metrics.jsonl").exists() and not (run / "tb").exists()
    assert upgrade(json.loads((run / "config.json").read_text()))["tensorboard"] is False
