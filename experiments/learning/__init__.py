"""How fast and why `main` learns to predict the next frame (LOG.md)."""
