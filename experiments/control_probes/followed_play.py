"""The privileged play, with a world model following it, that the probes of a world model's state
(`steering_probe.py`, `cdrl eval --imagination`) play on: `follow_step` and `start` of
`cdrl.evaluation.imagination_probe`, where they live."""
from cdrl.evaluation.imagination_probe import follow_step, start

__all__ = ["follow_step", "start"]
