"""features: keypoints + descriptors sampled anywhere, behind one small interface.

The built-in extractors (``alike`` and its variants ``alike-t/s/n/l``, ``aliked``, ``disk``, ``sift``,
``xfeat``) are imported on first use, so importing this package, and creating and using the SIFT
extractor, never imports torch. Their modules stay reachable as attributes
(``features.sift.octave_of_size``)."""

from __future__ import annotations

import importlib

from .base import (
    Extractor,
    ExtractorPolicy,
    Features,
    available,
    create,
    extractor_class,
    patch_offsets,
    policy_of,
    register,
)

__all__ = [
    "Extractor",
    "ExtractorPolicy",
    "Features",
    "available",
    "create",
    "extractor_class",
    "patch_offsets",
    "policy_of",
    "register",
]

_SUBMODULES = ("alike", "alike_net", "aliked", "aliked_net", "base", "disk", "heatmap", "packaged", "sift", "xfeat")


def __getattr__(name: str):  # PEP 562: load a built-in extractor's module (and torch, if it needs it) on use
    if name in _SUBMODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_SUBMODULES))
