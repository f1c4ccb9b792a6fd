"""The thesis's observation pre-processing as a pure function (numpy or jnp).

Raw RGB frame -> crop (central 300 x 300 of a 500 x 300 frame) -> mean over k x k
blocks (2 x 2 gives 150 x 150) -> max over the colour channels -> values in [0, 1].
"""

from __future__ import annotations

import numpy as np

DEFAULT_CROP = (0, 100, 300, 300)
DEFAULT_OUT_SIZE = (150, 150)


def central_crop(height: int, width: int, size: tuple[int, int]) -> tuple[int, int, int, int]:
    """The (top, left, h, w) box of a centred crop of ``size`` (h, w) in a frame."""
    h, w = size
    if h > height or w > width:
        raise ValueError(f"crop {size} larger than frame {(height, width)}")
    return ((height - h) // 2, (width - w) // 2, h, w)


def preprocess(frame, crop: tuple[int, int, int, int] | None = DEFAULT_CROP,
               out_size: tuple[int, int] = DEFAULT_OUT_SIZE):
    """Pre-processes RGB frames the way the thesis did.

    Args:
      frame: [..., H, W, C] array (numpy or jax; uint8 in 0..255 or float in [0, 1]).
        Leading batch dimensions are kept.
      crop: (top, left, height, width) box to keep, or None for the whole frame.
        The default is the central 300 x 300 of a 500 x 300 frame.
      out_size: (height, width) of the output; the crop must be an integer multiple
        of it along both axes (each output pixel is the mean of one block).
    Returns:
      [..., out_h, out_w] float32 in [0, 1]: the block means, then the max over
      channels.  A jax input gives a jax output, a numpy input a numpy output.
    """
    xp = _namespace(frame)
    if frame.ndim < 3:
        raise ValueError(f"frame must be [..., H, W, C], got shape {frame.shape}")
    height, width = frame.shape[-3], frame.shape[-2]
    top, left, h, w = (0, 0, height, width) if crop is None else crop
    if top < 0 or left < 0 or top + h > height or left + w > width:
        raise ValueError(f"crop {crop} outside frame of size {(height, width)}")
    oh, ow = out_size
    if h % oh or w % ow:
        raise ValueError(f"crop size {(h, w)} is not a multiple of out_size {out_size}")
    by, bx = h // oh, w // ow
    scale = 1.0 / 255.0 if frame.dtype == np.uint8 else 1.0
    x = frame[..., top:top + h, left:left + w, :].astype(xp.float32)
    lead = x.shape[:-3]
    x = x.reshape(lead + (oh, by, ow, bx, x.shape[-1]))
    x = x.mean(axis=(-4, -2))
    return xp.clip(x.max(axis=-1) * scale, 0.0, 1.0).astype(xp.float32)


def _namespace(frame):
    if isinstance(frame, np.ndarray):
        return np
    import jax.numpy as jnp

    return jnp
