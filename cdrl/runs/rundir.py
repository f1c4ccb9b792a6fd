"""The run directory: one place that knows what a run writes and how.

    config.json       the full resolved `RunConfig`
    data.json         the fingerprint of the episodes it trains on (`cdrl.data.fingerprint`),
                      checked when it resumes, and the changes a resume was allowed to take
    metrics.jsonl     one record per training step (loss, terms, norm ratios, frames/s)
    eval.jsonl        held-out evaluations (or policy comparisons for controller runs)
    checkpoints/      orbax checkpoints (`cdrl.runs.checkpoint`)
    plots/            figures written by `cdrl plot`
    tb/               TensorBoard event files (`cdrl.runs.tboard`)
    .lock             the writer's lock (`cdrl.data.lock`): its pid while it runs

Runs that collect the built-in game's data cache it beside them, in `../data-cache/`
(`RunDir.data_cache`), so runs in one directory share it.

Offline runs, online runs and every configuration of a sweep use `RunDir`; readers
(`cdrl eval`, `cdrl plot`, `cdrl.analysis.report`) read through it too. A writer holds
`RunDir.lock()` for as long as it writes; readers never take it and read only complete
records (`RunLog.read`).
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from cdrl.data import fingerprint
from cdrl.data.atomic import atomic_write_text  # noqa: F401  (re-exported: how a run's files are written)
from cdrl.data.lock import DirLock
from cdrl.runs.checkpoint import CheckpointError, Checkpoints
from cdrl.runs.config import RESUMABLE, RunConfig, saved_config, upgrade


class RunLog:
    """An append-only JSON-lines file of records with a `step`, cut back to a step on resume."""

    def __init__(self, path: Path):
        self.path = path

    def read(self) -> list[dict]:
        """The complete records. A truncated last line (a write cut off by a kill) is dropped;
        a malformed line elsewhere is an error naming the file and line."""
        if not self.path.is_file():
            return []
        lines = [line for line in self.path.read_text().splitlines() if line.strip()]
        records = []
        for i, line in enumerate(lines):
            try:
                record = json.loads(line)
            except json.JSONDecodeError as exc:
                if i == len(lines) - 1:
                    break
                raise ValueError(f"{self.path}: line {i + 1} is not valid JSON ({exc})") from None
            if not (isinstance(record, dict) and isinstance(record.get("step"), int)):
                raise ValueError(f"{self.path}: line {i + 1} is not a record of a step (a JSON object with an "
                                 "integer 'step')")
            records.append(record)
        return records

    def truncate(self, before_step: int) -> None:
        """Keep only the records of steps before `before_step` (and drop a torn last line)."""
        if not self.path.exists():
            return
        keep = [r for r in self.read() if r["step"] < before_step]
        atomic_write_text(self.path, "".join(json.dumps(r) + "\n" for r in keep))

    def append(self, records: list[dict]) -> None:
        with open(self.path, "a") as f:
            for record in records:
                f.write(json.dumps(record) + "\n")


def _check_compatible(cfg: RunConfig):
    # A field the checkpoint's config lacks (added to RunConfig later) had its thesis value.
    defaults = dataclasses.asdict(saved_config({}))

    def check(meta):
        saved = {**defaults, **upgrade(meta.get("config", {}))}
        diffs = [
            f"{k}: checkpoint has {saved[k]!r}, run has {v!r}"
            for k, v in dataclasses.asdict(cfg).items()
            if k not in RESUMABLE and saved[k] != v
        ]
        if diffs:
            raise CheckpointError("the checkpoint comes from an incompatible config: " + "; ".join(diffs))

    return check


class DataChangedError(ValueError):
    """The episodes a resumed run would train on are not those it started with."""


@dataclasses.dataclass(frozen=True)
class Opened:
    """A run ready to train: its state (restored when resuming), the step to start from, the
    checkpoint's metadata (None for a fresh run) and the checkpoints."""

    state: Any
    start: int
    meta: dict | None
    checkpoints: Checkpoints


class RunDir:
    """The files of one run (see the module docstring)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.config_path = self.path / "config.json"
        self.data_path = self.path / "data.json"
        self.metrics = RunLog(self.path / "metrics.jsonl")
        self.evals = RunLog(self.path / "eval.jsonl")
        self.checkpoint_dir = self.path / "checkpoints"
        self.plots_dir = self.path / "plots"
        self.tb_dir = self.path / "tb"
        self.data_cache = self.path.parent / "data-cache"

    def __repr__(self) -> str:
        return f"RunDir({str(self.path)!r})"

    def lock(self) -> DirLock:
        """The one-writer lock of this directory (not yet acquired: use `with run.lock():`);
        a second writer gets `cdrl.data.lock.LockedError` naming the holder's pid."""
        return DirLock(self.path, "run directory")

    def has_run(self) -> bool:
        return self.config_path.is_file()

    def read_config(self) -> RunConfig:
        """The run's config. FileNotFoundError if the directory does not exist, ValueError if
        it holds no run or its config.json is not a valid one."""
        if not self.path.is_dir():
            raise FileNotFoundError(f"run directory {self.path} {'is a file' if self.path.exists() else 'does not exist'}")
        if not self.config_path.is_file():
            raise ValueError(f"{self.path} is not a run directory: it has no config.json "
                                    "(make one with `cdrl train --run-dir`)")
        try:
            return saved_config(json.loads(self.config_path.read_text()))
        except (json.JSONDecodeError, TypeError) as exc:
            raise ValueError(f"{self.config_path} is not a valid run config: {exc}") from None

    def write_config(self, cfg: RunConfig) -> None:
        self.path.mkdir(parents=True, exist_ok=True)
        try:
            text = json.dumps(cfg.to_dict(), indent=2, allow_nan=False)
        except ValueError:
            raise ValueError(f"the config of {self.path} holds a number that is not finite; config.json holds "
                             "JSON numbers only") from None
        atomic_write_text(self.config_path, text + "\n")

    def check_data(self, data: dict, allow_change: bool = False) -> list[str]:
        """How the fingerprint `data` of the episodes a resume would train on differs from the
        one in data.json (nothing: the run kept none). A change raises `DataChangedError`
        naming it, unless `allow_change`; then the changes are returned, for `write_data`."""
        if not self.data_path.is_file():
            return []
        try:
            saved = json.loads(self.data_path.read_text())["fingerprint"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"{self.data_path} is not a valid data fingerprint ({exc}); remove it to record the "
                             "data afresh") from None
        changed = fingerprint.changes(saved, data)
        if changed and not allow_change:
            raise DataChangedError(
                f"the data of run {self.path} changed since the run recorded it in {self.data_path}: "
                f"{'; '.join(changed)}. Resuming would train on other episodes than the run did; resume with "
                "--allow-data-change to go on with the changed data (recorded in data.json)")
        return changed

    def write_data(self, data: dict, step: int, changed: list[str], fresh: bool = False) -> None:
        """Record `data` as the fingerprint of the run's episodes from `step` on (`fresh`: a new
        run); `changed`: how it differs from the one before (a resume allowed to change them)."""
        known = self.data_path.is_file() and not fresh
        if known and not changed:
            return
        history = json.loads(self.data_path.read_text()).get("changes", []) if known else []
        if changed:
            history.append({"step": step, "allowed": "--allow-data-change", "changes": changed})
        atomic_write_text(self.data_path, json.dumps({"fingerprint": data, "changes": history}, indent=1) + "\n")

    def config_for(self, cfg: RunConfig | None, resume: bool, overrides: dict | None = None) -> RunConfig:
        """The config a `train` of this directory runs with: `cfg` for a new run (refused if
        the directory already holds one), the saved config with `overrides` when resuming."""
        if resume:
            if not self.has_run():
                raise FileNotFoundError(f"cannot resume: {self.config_path} does not exist")
            saved = dataclasses.asdict(self.read_config())
            return RunConfig(**{**saved, **(overrides or {})})
        if cfg is None:
            raise ValueError("a new run needs a config (or resume an existing one)")
        if self.has_run():
            raise FileExistsError(f"{self.path} already holds a run; use --resume to continue it or pick another --run-dir")
        return cfg

    def checkpoints(self, keep: int = 3, primary: int = 0) -> Checkpoints:
        """The run's checkpoints; `primary`: the process that writes their metadata."""
        return Checkpoints(self.checkpoint_dir, keep=keep, primary=primary)

    def read_checkpoints(self) -> Checkpoints:
        """The run's checkpoints for reading only, safe beside a writer that is still training."""
        return Checkpoints(self.checkpoint_dir, read_only=True)

    def open(self, cfg: RunConfig, state, resume: bool, write: bool = True, data: dict | None = None,
             allow_data_change: bool = False) -> Opened:
        """Write the config and, when resuming, restore `state` from the last good checkpoint
        (an older one if the newest is corrupt) and cut the logs back to it. `data`: the
        fingerprint of the episodes the run trains on (None: it plays the game), recorded in
        data.json; a resume whose data changed is refused before anything is written, unless
        `allow_data_change`. With several processes every one restores and only the one that
        writes (`write`) touches files."""
        changed = self.check_data(data, allow_data_change) if resume and data is not None else []
        ckpts = self.checkpoints(cfg.keep_checkpoints)
        start, meta = 0, None
        if resume and ckpts.steps():
            state, meta = ckpts.restore_newest(state, check_meta=_check_compatible(cfg), say=write)
            start = int(meta["step"])
        if write:
            self.write_config(cfg)
            if data is not None:
                self.write_data(data, start, changed, fresh=not resume)
            self.metrics.truncate(start)
            self.evals.truncate(start + 1)
        return Opened(state=state, start=start, meta=meta, checkpoints=ckpts)
