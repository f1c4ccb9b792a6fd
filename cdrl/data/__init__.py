"""Data: the `Episode` unit (`episode`), on-disk data sets and their collection (`store`),
T-step chunks of B streams for truncated BPTT (`stream`), synthetic episodes (`synthetic`)
and frame conversions (`frames`)."""
