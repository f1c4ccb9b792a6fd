"""Checkpoints of a training run with orbax: the whole training state (a `TrainState`:
parameters, optimiser state, every stream's carry, step; or an online run's `OnlineState`)
plus JSON metadata (the run config, the data cursor, the
PRNG key). Orbax writes each checkpoint to a temporary directory and renames it when
complete, so an interrupted save never replaces a good checkpoint; the last k are kept.
Each finished checkpoint then gets the checksums of its files (`cdrl.runs.checksums`), and
every restore checks them first: a flipped bit is a corrupt checkpoint, never a slightly
different state. Restoring the newest good checkpoint skips corrupt ones with one line each.

With several processes (`jax.distributed`) a save and a restore are collective: every process
calls them with the same global arrays, each writes its shards (orbax's multi-process
checkpointing), and the `primary` process writes the metadata and the JSON (process 0 for a
data-parallel run; in a sweep, the process that holds the configuration, which alone knows
its data cursor).
"""
from __future__ import annotations

import contextlib
import gc
import logging
import shutil
import sys
from pathlib import Path
from typing import Any

import jax
import orbax.checkpoint as ocp

from cdrl.runs import checksums


logging.getLogger("absl").setLevel(logging.WARNING)


def _with_sharding(leaf) -> jax.ShapeDtypeStruct:
    struct = ocp.utils.to_shape_dtype_struct(leaf)
    if getattr(struct, "sharding", None) is None:
        struct = jax.ShapeDtypeStruct(struct.shape, struct.dtype,
                                      sharding=jax.sharding.SingleDeviceSharding(jax.local_devices()[0]))
    return struct


class CheckpointError(RuntimeError):
    """No usable checkpoint, or one from an incompatible configuration."""


class CorruptCheckpointError(CheckpointError):
    """A checkpoint's files do not match their checksums, or it lacks them (its save did not finish)."""


# The metadata key that says a checkpoint's save writes checksums (a checkpoint written before
# they existed has none and restores unchecked).
CHECKSUMMED = "checksums"


def _first_line(exc: BaseException, limit: int = 200) -> str:
    text = (str(exc).strip().splitlines() or [""])[0]
    return f"{type(exc).__name__}: {text[:limit]}{'...' if len(text) > limit else ''}"


def _drops_closed_loop_callback(unraisable) -> bool:
    return isinstance(unraisable.exc_value, RuntimeError) and str(unraisable.exc_value) == "Event loop is closed"


def _unawaited(record: logging.LogRecord) -> bool:
    """False for asyncio's report of an exception nobody awaited (its first line; the next name
    the future)."""
    first_line = record.getMessage().partition("\n")[0]
    return first_line not in ("Future exception was never retrieved", "Task exception was never retrieved")


class _ClosedLoopCallbacks:
    """What orbax leaves behind when it reads a checkpoint it cannot restore: orbax runs each
    restore in an event loop of its own (`asyncio_utils.run_sync`) and closes it as soon as the
    first array read fails, while tensorstore's reads of the other arrays are still pending; each
    of them completes into the closed loop and its callback's `RuntimeError: Event loop is
    closed` reaches `sys.unraisablehook`, a traceback each; the reads that failed as the first
    one did are futures nobody awaits, and asyncio logs each ('Future/Task exception was never
    retrieved') when it is collected, which can be after the restore has returned (tensorstore's
    threads hold the last references). So: dropped while checkpoints are read, and for the rest
    of the process once a read has failed there; nothing else is dropped. A checkpoint with
    checksums is checked before orbax reads it, so this is for those written without."""

    def __init__(self):
        self.previous_hook, self.kept = None, False

    def hook(self, unraisable):
        if not _drops_closed_loop_callback(unraisable):
            self.previous_hook(unraisable)

    @contextlib.contextmanager
    def dropped(self):
        """Drop them while the block reads; `keep()` inside it leaves them dropped for good."""
        if self.kept:
            yield self
            return
        self.previous_hook = sys.unraisablehook
        sys.unraisablehook = self.hook
        logging.getLogger("asyncio").addFilter(_unawaited)
        try:
            yield self
        finally:
            gc.collect()
            if not self.kept:
                logging.getLogger("asyncio").removeFilter(_unawaited)
                sys.unraisablehook = self.previous_hook

    def keep(self):
        self.kept = True


_CLOSED_LOOP_CALLBACKS = _ClosedLoopCallbacks()


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
            old, self.manager = self.manager, self._open_reader()
            old.close()
        return sorted(self.manager.all_steps())

    def close(self) -> None:
        self.manager.close()

    def save(self, step: int, state, meta: dict[str, Any]) -> None:
        """Save `state` as checkpoint `step`, replacing a stale one of the same step (left by a
        corrupt checkpoint that a resumed run has reached again). A write that fails (a full
        disk) raises `CheckpointError` naming the checkpoint; its partial temporary directory is
        removed and the earlier checkpoints are left as they were. The primary process then
        writes the checksums of the checkpoint's files into it (`cdrl.runs.checksums`)."""
        if step in self.manager.all_steps():
            self.manager.delete(step)
        self._remove_temporary(step)  # left by a save that failed or was killed
        meta = {**meta, CHECKSUMMED: checksums.ALGORITHM}
        try:
            self.manager.save(
                step,
                args=ocp.args.Composite(state=ocp.args.StandardSave(state), meta=ocp.args.JsonSave(meta)),
                force=True,
            )
            self.manager.wait_until_finished()
            if self._is_primary():
                checksums.write_checksums(self.directory / str(step))
        except OSError as exc:
            self._discard_partial(step)
            kept = ", ".join(map(str, self.steps())) or "none"
            raise CheckpointError(
                f"could not write checkpoint {self.directory / str(step)}: {exc.strerror or exc}; the earlier "
                f"checkpoints are intact (steps: {kept}) and a resumed run starts from the newest") from exc

    def _discard_partial(self, step: int) -> None:
        try:
            self.manager.wait_until_finished()
            if self._is_primary() and step in self.manager.all_steps():  # committed, without checksums
                self.manager.delete(step)
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

    def verify(self, step: int, meta: dict | None = None) -> bool:
        """Check checkpoint `step`'s files against their checksums; `meta`: its metadata if read
        already. Returns False for a checkpoint written before checksums existed (nothing to
        check). Raises `CorruptCheckpointError` naming the checkpoint and the file."""
        path = self.directory / str(step)
        if not checksums.has_checksums(path):
            if (self.read_meta(step) if meta is None else meta).get(CHECKSUMMED):
                raise CorruptCheckpointError(f"checkpoint {path} is unfinished: its save wrote no checksums")
            return False
        try:
            checksums.verify(path)
        except checksums.ChecksumError as exc:
            raise CorruptCheckpointError(f"checkpoint {path} is corrupt: {exc}") from None
        return True

    def restore(self, step: int, like):
        """The state saved at `step`, shaped like `like` (an abstract or concrete state), on
        the shardings of `like` (this process's first device for a leaf without one), after
        checking its checksums (`verify`)."""
        self.verify(step)
        return self._restore(step, like)

    def _restore(self, step: int, like):
        abstract = jax.tree.map(_with_sharding, like)
        restored = self.manager.restore(
            step,
            args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract), meta=ocp.args.JsonRestore()),
        )
        return restored["state"], restored["meta"]

    def restore_latest_good(self, like, check_meta=None) -> tuple[Any, dict[str, Any], list[str]]:
        """The newest checkpoint that restores cleanly; older ones are tried when a newer one is
        corrupt. `check_meta(meta)` may raise `CheckpointError` for an incompatible config
        (that is not skipped: it is an error). Returns (state, meta, warnings), a warning per
        checkpoint skipped (`restore_newest` prints them)."""
        for _ in range(VANISHED_RETRIES):
            steps = self.steps()
            if not steps:
                raise CheckpointError(f"no checkpoint found in {self.directory}")
            with _CLOSED_LOOP_CALLBACKS.dropped() as callbacks:
                found, warnings = self._newest_good(steps, like, check_meta, callbacks.keep)
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

    def _newest_good(self, steps: list[int], like, check_meta, read_failed):
        """((state, meta) of the newest of `steps` that restores, or None; warnings), or
        (_VANISHED, ...) when a checkpoint disappeared while it was read: a live writer rotated
        it away, and a new listing holds a newer one. Not a corruption, so no warning.
        `read_failed()` is called when orbax failed to read a checkpoint's arrays."""
        warnings = []
        for step in reversed(steps):
            path = self.directory / str(step)
            try:
                meta = self.read_meta(step)
                self.verify(step, meta)
            except CorruptCheckpointError as exc:
                if not path.exists():
                    return _VANISHED, warnings
                warnings.append(str(exc))
                continue
            except Exception as exc:  # noqa: BLE001 - any read failure means this one is unusable
                if not path.exists():
                    return _VANISHED, warnings
                warnings.append(f"checkpoint {path} is unreadable ({_first_line(exc)})")
                continue
            if check_meta is not None:
                check_meta(meta)
            try:
                return self._restore(step, like), warnings
            except Exception as exc:  # noqa: BLE001
                read_failed()
                if not path.exists():
                    return _VANISHED, warnings
                warnings.append(f"checkpoint {path} is corrupt ({_first_line(exc)})")
        return None, warnings

    def restore_newest(self, like, check_meta=None, say: bool = True) -> tuple[Any, dict[str, Any]]:
        """`restore_latest_good`, each checkpoint it skipped named on stderr in one line with the
        one it restored instead (`say`: this process prints): what `cdrl train --resume`,
        `cdrl eval` and `cdrl plot` restore with."""
        state, meta, warnings = self.restore_latest_good(like, check_meta)
        for warning in warnings if say else ():
            print(f"warning: {warning}; restored the older checkpoint {meta.get('step')} instead", file=sys.stderr)
        return state, meta
