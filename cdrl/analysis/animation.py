"""Animated GIFs of PIL images: the imagination video and the policy video share one writer."""
from __future__ import annotations

from pathlib import Path


def write_gif(images: list, path: Path, frame_ms: int) -> Path:
    """`images` as an animated GIF at `path`, `frame_ms` per frame, looping."""
    path = Path(path)
    images[0].save(path, save_all=True, append_images=images[1:], duration=frame_ms, loop=0)
    return path
