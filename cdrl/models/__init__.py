"""The models: architecture presets (`arch`), networks (`nets`), the variant contract
(`base`), the observation variants (`observation`), the controller variants (`controller`),
and the registry of every variant by name.

The registry is explicit: `VARIANTS` lists the classes of both modules; `register` adds a
variant of your own (usable as a class decorator), `make_variant(name, arch)` builds one.
"""
from __future__ import annotations

from cdrl.models.arch import PRESETS, SMALL, THESIS, TINY, ArchConfig, ConvSpec, preset
from cdrl.models.base import StepInput, Variant
from cdrl.models.controller import CONTROLLER_VARIANTS
from cdrl.models.observation import OBSERVATION_VARIANTS
from cdrl.models import onednn_layers  # noqa: F401 (registers `--conv onednn`'s layers with cdrl.models.conv)

VARIANTS: dict[str, type[Variant]] = {cls.name: cls for cls in OBSERVATION_VARIANTS + CONTROLLER_VARIANTS}


def register(cls: type[Variant]) -> type[Variant]:
    """Add a variant class to the registry under its `name` (usable as a decorator)."""
    if not cls.name:
        raise ValueError(f"{cls.__name__} needs a non-empty `name`")
    if cls.name in VARIANTS and VARIANTS[cls.name] is not cls:
        raise ValueError(f"a variant named {cls.name!r} is already registered")
    VARIANTS[cls.name] = cls
    return cls


def make_variant(name: str, arch: ArchConfig) -> Variant:
    """The variant called `name` for architecture `arch`."""
    try:
        cls = VARIANTS[name]
    except KeyError:
        raise ValueError(f"unknown variant {name!r}; choose one of {sorted(VARIANTS)}") from None
    return cls(arch)


__all__ = ["ArchConfig", "ConvSpec", "PRESETS", "SMALL", "StepInput", "THESIS", "TINY", "VARIANTS", "Variant",
           "make_variant", "preset", "register"]
