"""The feature-extractor interface and its registry.

An extractor finds keypoints in an image and can sample its descriptor field at *arbitrary* pixel
positions, which is what the S x S descriptor patches of the method need. Keypoints use COLMAP's
pixel convention (centre of the top-left pixel = (0.5, 0.5)). Descriptors are L2-normalised.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ..errors import InputError


@dataclass
class Features:
    """What an extractor returns for one image."""

    keypoints: np.ndarray  # (N, 2) float32, pixels (COLMAP convention)
    scores: np.ndarray  # (N,) float32
    descriptors: np.ndarray  # (N, C) float32, unit norm
    image_size: tuple[int, int]  # (width, height)
    dense: Any = None  # extractor-specific state used by Extractor.sample (e.g. a dense map)

    def __len__(self) -> int:
        return len(self.keypoints)


class Extractor(ABC):
    name: str = ""
    channels: int = 0
    match_ratio: float = 1.0  # default Lowe ratio for matching these descriptors (1: no ratio test)

    def __init__(self, max_keypoints: int = 2048, device: str | None = None):
        self.max_keypoints = int(max_keypoints)
        self.device = device or "cpu"

    @abstractmethod
    def extract(self, image: np.ndarray) -> Features:
        """Keypoints and descriptors of an RGB uint8 image (H, W, 3)."""

    @abstractmethod
    def sample(self, features: Features, points: np.ndarray) -> np.ndarray:
        """Descriptors (P, C) float32 at pixel positions ``points`` (P, 2) of the same image."""

    def config(self) -> dict:
        return {"name": self.name, "channels": self.channels, "max_keypoints": self.max_keypoints}


_REGISTRY: dict[str, Callable[..., Extractor]] = {}


def register(name: str):
    """Class decorator: make an extractor available by name."""

    def deco(cls):
        cls.name = name
        _REGISTRY[name] = cls
        return cls

    return deco


def available() -> list[str]:
    return sorted(_REGISTRY)


def create(name: str, **kwargs) -> Extractor:
    if name not in _REGISTRY:
        raise InputError(f"unknown feature extractor {name!r} (available: {', '.join(available())})")
    return _REGISTRY[name](**kwargs)


def patch_offsets(size: int) -> np.ndarray:
    """(S*S, 2) pixel offsets of an S x S patch centred on 0, row-major (v, then u)."""
    r = (np.arange(size) - (size - 1) / 2.0).astype(np.float32)
    vv, uu = np.meshgrid(r, r, indexing="ij")
    return np.stack([uu.ravel(), vv.ravel()], axis=1)


def subpixel_offsets(heat: torch.Tensor, kpts: torch.Tensor) -> torch.Tensor:
    """Sub-pixel refinement of heatmap maxima: a 1D parabola through the peak and its two
    neighbours along x and along y (offsets clamped to half a pixel). ``kpts`` (N, 2) are integer
    (x, y) positions in the heatmap's pixels; returns (N, 2) offsets to add to them."""
    H, W = heat.shape
    x = kpts[:, 0].long().clamp(1, W - 2)
    y = kpts[:, 1].long().clamp(1, H - 2)
    c = heat[y, x]
    off = []
    for lo, hi in ((heat[y, x - 1], heat[y, x + 1]), (heat[y - 1, x], heat[y + 1, x])):
        den = 2 * c - lo - hi
        d = torch.where(den > 1e-12, 0.5 * (hi - lo) / den.clamp_min(1e-12), torch.zeros_like(c))
        off.append(d.clamp(-0.5, 0.5))
    inside = ((kpts[:, 0] >= 1) & (kpts[:, 0] <= W - 2) & (kpts[:, 1] >= 1) & (kpts[:, 1] <= H - 2)).float()
    return torch.stack(off, 1) * inside[:, None]
