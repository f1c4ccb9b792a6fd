"""The controller study: model-based controllers against PPO and scripted policies (LOG.md)."""
