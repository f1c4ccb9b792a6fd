"""Evaluation: next-frame scores on held-out episodes against the copy-last-frame baseline
and the entropy floor (`metrics`), and playing policies in the game (`play`)."""
