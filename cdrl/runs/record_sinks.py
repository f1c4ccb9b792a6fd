"""`RunWriter`: the host loop's sink of one run directory (`cdrl.training.loop.Sink`).

Step records go to TensorBoard at once and to `metrics.jsonl` at every flush (before each
checkpoint and at the end), so the log never runs ahead of the newest checkpoint by more than
the steps since it; evaluation records go to `eval.jsonl` and TensorBoard at once, with an
image (held-out frames above the model's predictions of them) where the job draws one. A
resumed writer purges TensorBoard's events from its start step and writes again the kept
evaluations of that step (`TBLog.replay_evals`).
"""
from __future__ import annotations

import numpy as np

from cdrl.runs.rundir import RunDir
from cdrl.runs.tboard import TBLog
from cdrl.training.loop import NullSink, Sink


class RunWriter(Sink):
    """Writes one lane's records into `run` (see the module docstring)."""

    def __init__(self, run: RunDir, start: int, tensorboard: bool):
        self.run, self.pending = run, []
        self.tb = TBLog(run.tb_dir, start, tensorboard)
        self.replayed = self.tb.replay_evals(run.evals.read(), start)

    def step(self, record: dict) -> None:
        self.pending.append(record)
        self.tb.step(record)

    def evaluation(self, record: dict, image: np.ndarray | None = None) -> None:
        self.run.evals.append([record])
        self.tb.eval(record)
        if image is not None:
            self.tb.image(int(record["step"]), image)
        self.tb.flush()

    def image(self, step: int, image: np.ndarray) -> None:
        self.tb.image(step, image)

    def flush(self) -> None:
        self.run.metrics.append(self.pending)
        self.pending = []
        self.tb.flush()

    def close(self) -> None:
        self.flush()
        self.tb.close()


def run_writer(run: RunDir, start: int, tensorboard: bool, writes: bool = True) -> Sink:
    """A `RunWriter` of `run`, or a `NullSink` for a process that does not write its files."""
    return RunWriter(run, start, tensorboard) if writes else NullSink()
