"""Checkpoints of a training run with orbax: the whole training state (a `TrainState`:
parameters, optimiser state, every stream's carry, step; or an online run's `OnlineState`)
plus JSON metadata (the run config, the data cursor, the
PRNG key). Orbax writes each checkpoint to a temporary directory and renames it when
complete, so an interrupted save never replaces a good checkpoint; the last k are kept.

With several processes (`jax.distributed`) a save and a restore are collective: every process
calls them with the same global arrays, each writes its shards (orbax's multi-process
checkpointing), and the `primary` process writes the metadata and the JSON (process 0 for a
data-parallel run; in a sweep, the process that holds the configuration, which alone knows
its data cursor).
"""
from __future__ import annotations

import logging
import shutil
from pathlib import Path
from typing import Any

import jax
import orbax.checkpoint as ocp


logging.getLogger("absl").setLevel(logging.WARNING)


def _with_sharding(leaf) -> jax.ShapeDtypeStruct:
    struct = ocp.utils.to_shape_dtype_struct(leaf)
    if getattr(struct, "sharding", None) is None:
        struct = jax.ShapeDtypeStruct(struct.shape, struct.dtype,
                                      sharding=jax.sharding.SingleDeviceSharding(jax.local_devices()[0]))
    return struct


class CheckpointError(RuntimeError):
    """No usable checkpoint, or one from an incompatible configuration."""


# How many times a reader lists the checkpoints again after one it was reading was removed.
VANISHED_RETRIES = 5
_VANISHED = object()


class Checkpoints:
    """Save and restore training states (any pytree) and their metadata under `directory`."""

    def __init__(self, directory: str | Path, keep: int = 3, primary: int = 0, read_only: bool = False):
        """`read_only`: for a process that does not own the run (evaluation, figures) while its
        writer may still be training: nothing is created, rotated or deleted, and the list of
        checkpoints is read afresh each time, since the writer's rotation removes old ones."""
        self.directory = Path(directory).absolute()
        self.primary = primary
        self.read_only = read_only
        if read_only:
            self.manager = self._open_reader()
            return
        if primary == 0:
            options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=True, enable_async_checkpointing=False)
            self.manager = ocp.CheckpointManager(self.directory, options=options)
            return
        processes = ocp.options.MultiprocessingOptions(primary_host=primary)
        options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=True, enable_async_checkpointing=False,
                                               multiprocessing_options=processes)
        handlers = {"state": ocp.StandardCheckpointHandler(multiprocessing_options=processes),
                    "meta": ocp.JsonCheckpointHandler(multiprocessing_options=processes)}
        self.manager = ocp.CheckpointManager(self.directory, options=options, item_handlers=handlers)

    def _open_reader(self) -> ocp.CheckpointManager:
        """A read-only manager. Without `lightweight_initialize` it would read every checkpoint's
        metadata when it lists them (orbax's `reload` too) and fail on one that the writer
        removes meanwhile. Orbax warns that read-only mode is on; that is no news here."""
        options = ocp.CheckpointManagerOptions(read_only=True, lightweight_initialize=True, save_interval_steps=0,
                                               create=False, enable_async_checkpointing=False)
        absl = logging.getLogger("absl")
        level = absl.level
        absl.setLevel(logging.ERROR)
        try:
            return ocp.CheckpointManager(self.directory, options=options)
        finally:
            absl.setLevel(level)

    def _is_primary(self) -> bool:
        return jax.process_index() == self.primary

    def steps(self) -> list[int]:
        if self.read_only:  # a fresh listing: a live writer saves and rotates meanwhile
            self.manager = self._open_reader()
        return sorted(self.manager.all_steps())

    def save(self, step: int, state, meta: dict[str, Any]) -> None:
        """Save `state` as checkpoint `step`, replacing a stale one of the same step (left by a
        corrupt checkpoint that a resumed run has reached again). A write that fails (a full
        disk) raises `CheckpointError` naming the checkpoint; its partial temporary directory is
        removed and the earlier checkpoints are left as they were."""
        if step in self.manager.all_steps():
            self.manager.delete(step)
        self._remove_temporary(step)  # left by a save that failed or was killed
        try:
            self.manager.save(
                step,
                args=ocp.args.Composite(state=ocp.args.StandardSave(state), meta=ocp.args.JsonSave(meta)),
                force=True,
            )
            self.manager.wait_until_finished()
        except OSError as exc:
            self._discard_partial(step)
            kept = ", ".join(map(str, self.steps())) or "none"
            raise CheckpointError(
                f"could not write checkpoint {self.directory / str(step)}: {exc.strerror or exc}; the earlier "
                f"checkpoints are intact (steps: {kept}) and a resumed run starts from the newest") from exc

    def _discard_partial(self, step: int) -> None:
        try:
            self.manager.wait_until_finished()
        except Exception:  # noqa: BLE001 - the save already failed; only its leftovers matter now
            pass
        self._remove_temporary(step)

    def _remove_temporary(self, step: int) -> None:
        """Remove the temporary directory of an unfinished save of `step` (orbax writes a
        checkpoint to '<step>.orbax-checkpoint-tmp*' and renames it when complete)."""
        if not self._is_primary():
            return
        for path in self.directory.glob(f"{step}.orbax-checkpoint-tmp*"):
            shutil.rmtree(path, ignore_errors=True)

    def read_meta(self, step: int) -> dict[str, Any]:
        restored = self.manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))
        return restored["meta"]

    def restore(self, step: int, like):
        """The state saved at `step`, shaped like `like` (an abstract or concrete state), on
        the shardings of `like` (this process's first device for a leaf without one)."""
        abstract = jax.tree.map(_with_sharding, like)
        restored = self.manager.restore(
            step,
            args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract), meta=ocp.args.JsonRestore()),
        )
        return restored["state"], restored["meta"]

    def restore_latest_good(self, like, check_meta=None) -> tuple[Any, dict[str, Any], list[str]]:
        """The newest checkpoint that restores cleanly; older ones are tried when a newer one is
        corrupt. `check_meta(meta)` may raise `CheckpointError` for an incompatible config
        (that is not skipped: it is an error). Returns (state, meta, warnings)."""
        for _ in range(VANISHED_RETRIES):
            steps = self.steps()
            if not steps:
                raise CheckpointError(f"no checkpoint found in {self.directory}")
            found, warnings = self._newest_good(steps, like, check_meta)
            if found is not _VANISHED:
                break
        else:
            raise CheckpointError(f"the checkpoints in {self.directory} kept being removed while they were read "
                                  f"({VANISHED_RETRIES} listings): is a run rotating them very fast?")
        if found is not None:
            return (*found, warnings)
        raise CheckpointError(
            f"every checkpoint in {self.directory} is corrupt or unreadable:\n  " + "\n  ".join(warnings)
        )

    def _newest_good(self, steps: list[int], like, check_meta):
        """((state, meta) of the newest of `steps` that restores, or None; warnings), or
        (_VANISHED, ...) when a checkpoint disappeared while it was read: a live writer rotated
        it away, and a new listing holds a newer one. Not a corruption, so no warning."""
        warnings = []
        for step in reversed(steps):
            path = self.directory / str(step)
            try:
                meta = self.read_meta(step)
            except Exception as exc:  # noqa: BLE001 - any read failure means this one is unusable
                if not path.exists():
                    return _VANISHED, warnings
                warnings.append(f"checkpoint {path} is unreadable ({type(exc).__name__}: {exc})")
                continue
            if check_meta is not None:
                check_meta(meta)
            try:
                return self.restore(step, like), warnings
            except Exception as exc:  # noqa: BLE001
                if not path.exists():
                    return _VANISHED, warnings
                warnings.append(f"checkpoint {path} is corrupt ({type(exc).__name__}: {exc})")
        return None, warnings
