"""Offline world models: multi-step training and the variants at the thesis's size (LOG.md)."""
