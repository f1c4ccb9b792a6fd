"""Evaluation: next-frame scores on held-out episodes against the copy-last-frame baseline
and the entropy floor (`metrics`), playing policies in the game (`play`), and figures across
seeds with their confidence intervals (`stats`)."""
