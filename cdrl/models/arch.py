"""Static architecture configuration: frozen, hashable, usable as a `jit` static argument.

Sizes and layer tables live here; numbers that may vary inside one compiled program
(learning rate, momentum, loss weights) live in `cdrl.training.optim.HParams` instead.
"""
from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class ConvSpec:
    """One convolution of the observation encoder (the decoder mirrors it)."""

    features: int
    kernel: int
    stride: int
    padding: int

    def out_size(self, size: int) -> int:
        """Spatial output size of the convolution for a square input of `size`."""
        return (size + 2 * self.padding - self.kernel) // self.stride + 1

    def transposed_out_size(self, size: int) -> int:
        """Output size of the mirrored transposed convolution (PyTorch `ConvTranspose2d`)."""
        return (size - 1) * self.stride - 2 * self.padding + self.kernel


@dataclasses.dataclass(frozen=True)
class ArchConfig:
    """Every size of the networks.

    `encoder` is the observation encoder's layer table; the observation decoder is its exact
    mirror (transposed convolutions with the same kernel, stride and padding, in reverse).
    The last encoder layer's `features` is the observation code size.

    Two numbers are not sizes but fixed parts of the model that the thesis leaves at their
    neutral values: `obs_mean` / `obs_std`, the affine map applied to frames before the
    encoder (x - mean) / std (0 / 1: raw [0, 1] brightness, as in the thesis), and
    `fc_init_gain`, the scale of the LeCun-normal initial kernel of the FC layer that reads
    the LSTM's output (1: the thesis's initialisation).

    `conv` is not part of the model but how its convolutions are computed
    (`cdrl.models.conv.FORMULATIONS`): a static field, so a program compiled with one backend
    is never reused for another. Parameters, and so checkpoints, do not depend on it.

    `max_filter` is part of the pre-processing: where the game's 150 x 150 frame is shrunk to
    `image_size`, each of its pixels first becomes the brightest of the `max_filter` x
    `max_filter` window around it (`cdrl.data.frames.resize_obs`; 1: none, the plain area
    average).
    """

    image_size: int = 150
    encoder: tuple[ConvSpec, ...] = (
        ConvSpec(16, 4, 2, 2),
        ConvSpec(16, 4, 2, 1),
        ConvSpec(32, 4, 2, 2),
        ConvSpec(64, 4, 2, 1),
        ConvSpec(128, 4, 2, 1),
        ConvSpec(512, 5, 1, 0),
    )
    action_dim: int = 3
    action_hidden: tuple[int, ...] = (128, 128)
    action_code: int = 16
    reward_code: int = 16
    reward_hidden: int = 64
    lstm_size: int = 512
    obs_mean: float = 0.0
    obs_std: float = 1.0
    fc_init_gain: float = 1.0
    max_filter: int = 1
    conv: str = "auto"

    def __post_init__(self):
        if self.image_size < 1:
            raise ValueError(f"image_size must be >= 1, got {self.image_size}")
        if self.max_filter < 1:
            raise ValueError(f"max_filter must be >= 1 (1: none), got {self.max_filter}")
        if not self.encoder:
            raise ValueError("encoder must have at least one layer")
        sizes = self.encoder_sizes
        if sizes[-1] != 1:
            raise ValueError(
                f"encoder must reduce the {self.image_size}x{self.image_size} image to 1x1, "
                f"its layers give sizes {sizes}"
            )
        back = self.decoder_sizes
        if back[-1] != self.image_size:
            raise ValueError(
                f"the mirrored decoder must rebuild {self.image_size}x{self.image_size}, "
                f"its layers give sizes {back}"
            )

    @property
    def obs_code(self) -> int:
        return self.encoder[-1].features

    @property
    def encoder_sizes(self) -> tuple[int, ...]:
        """Spatial size after each encoder layer, starting with the input."""
        sizes = [self.image_size]
        for spec in self.encoder:
            sizes.append(spec.out_size(sizes[-1]))
        return tuple(sizes)

    @property
    def decoder_sizes(self) -> tuple[int, ...]:
        """Spatial size after each decoder layer, starting with the 1x1 code."""
        sizes = [1]
        for spec in reversed(self.encoder):
            sizes.append(spec.transposed_out_size(sizes[-1]))
        return tuple(sizes)


THESIS = ArchConfig()

SMALL = ArchConfig(
    image_size=64,
    encoder=(
        ConvSpec(8, 4, 2, 1),
        ConvSpec(16, 4, 2, 1),
        ConvSpec(32, 4, 2, 1),
        ConvSpec(64, 4, 2, 1),
        ConvSpec(128, 4, 1, 0),
    ),
    action_hidden=(64, 64),
    action_code=16,
    reward_code=16,
    reward_hidden=32,
    lstm_size=128,
)

# The small preset's networks on 128 x 128 frames: the first layer reads 8 x 8 windows at stride
# 4 to the same 32 x 32 x 8 that the small preset's first layer makes of 64 x 64, the rest (and
# the decoder's mirror) is the small preset's. At 64 x 64 the thesis level's pellets (radius 2 of the
# raw pixels) brighten about 4 pixels by a fifth of the range, at 128 x 128 about 8 by a half
# (`experiments/control_probes/pellet_contrast.py`).
SMALL_128 = dataclasses.replace(
    SMALL,
    image_size=128,
    encoder=(ConvSpec(8, 8, 4, 2),) + SMALL.encoder[1:],
)

# The small preset on frames shrunk after a 5 x 5 max filter: at 64 x 64 the thesis level's pellets
# then brighten about 15 pixels by three quarters of the range, as the pellets of level `visible`
# (drawn at a snake segment's radius) do at 64 x 64 without it, where the plain area average leaves
# 4 pixels at a fifth (`experiments/control_probes/pellet_contrast.py --max-filter 5`); the snakes widen by about
# one pixel.
SMALL_MAX = dataclasses.replace(SMALL, max_filter=5)

# A very small preset for gradient checks and unit tests.
TINY = ArchConfig(
    image_size=16,
    encoder=(ConvSpec(4, 4, 2, 1), ConvSpec(8, 4, 2, 1), ConvSpec(16, 4, 1, 0)),
    action_hidden=(16,),
    action_code=4,
    reward_code=4,
    reward_hidden=8,
    lstm_size=16,
)

PRESETS = {"thesis": THESIS, "small": SMALL, "small-128": SMALL_128, "small-max": SMALL_MAX, "tiny": TINY}


def preset(name: str) -> ArchConfig:
    """The architecture preset called `name` (one of `PRESETS`)."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(
            f"unknown architecture preset {name!r}; choose one of {sorted(PRESETS)}"
        ) from None
