"""Probes of what a controller could read from the frames and from a world model's state (LOG.md)."""
