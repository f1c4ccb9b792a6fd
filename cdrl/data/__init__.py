"""Data: the `Episode` unit (`episode`), on-disk data sets: their format and reader (`store`),
atomic file writes (`atomic`), the resumable, locked writer (`writer`, `lock`), collecting the
built-in game (`collect`) and recording any gymnasium game (`gymrec`); T-step chunks of B
streams for truncated BPTT (`stream`), synthetic episodes (`synthetic`) and frame conversions
(`frames`)."""
