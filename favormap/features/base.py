"""The feature-extractor interface and its registry.

An extractor finds keypoints in an image and can sample its descriptor field at *arbitrary* pixel
positions, which is what the S x S descriptor patches of the method need. Keypoints use COLMAP's
pixel convention (centre of the top-left pixel = (0.5, 0.5)). Descriptors are L2-normalised.
"""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

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


@dataclass(frozen=True)
class ExtractorPolicy:
    """How favormap builds and localizes with an extractor's features unless told otherwise.

    Each extractor class states its own as ``Extractor.policy``; one registered without it gets
    these defaults. The reasons for the built-in extractors' values are in
    docs/implementation-notes.md."""

    # the least epipolar limit of tracking (px at the working resolution; BuildConfig.max_epipolar_px):
    # how precisely the detector places a keypoint
    keypoint_precision_px: float = 1.0
    # radius of the observation patches a build stores in the map (BuildConfig.align_patches; 0: none);
    # > 0 also makes the map's localizer align the query keypoints to them (LocalizeConfig.align)
    align_patches: int = 0
    training_quality: str = "fast"  # the VoxelConfig preset a build trains with (favormap.voxels.QUALITY_PRESETS)
    # VoxelConfig.prior_mean_deg: the angle over which an extrapolated view's target descriptor moves from the
    # nearest training views to the track's mean (0: never)
    view_prior_deg: float = 30.0
    patch_interp: bool = False  # VoxelConfig.patch_interp: training patches described on a sub-grid
    match_threshold: float = 0.7  # cosine threshold of the localizer's descriptor matching
    match_ratio: float = 1.0  # Lowe ratio when a query is matched against the whole map (1: no ratio test)

    def __post_init__(self):
        if not self.keypoint_precision_px > 0:
            raise InputError(f"keypoint_precision_px must be > 0, not {self.keypoint_precision_px!r}")
        if not (isinstance(self.align_patches, int) and self.align_patches >= 0):
            raise InputError(f"align_patches must be an integer >= 0, not {self.align_patches!r}")
        if not (0 < self.match_ratio <= 1 and -1 <= self.match_threshold < 1):
            raise InputError("match_ratio must lie in (0, 1] and match_threshold in [-1, 1)")


class Extractor(ABC):
    name: str = ""
    channels: int = 0
    policy: ExtractorPolicy = ExtractorPolicy()
    # a torch model that runs on the build's device: one instance per device, shared by a build's threads
    # (inference does not change it); others (OpenCV's) get one instance per thread
    uses_device: bool = False
    # sample() can run on a GPU (SIFT: favormap.features.sift_torch), so the training patches are GPU tasks there
    samples_on_device: bool = False

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

    # The sampling state (``Features.dense``) as named NumPy arrays and back: what lets the on-disk
    # feature cache (:mod:`favormap.features.cache`) hold a frame's features instead of RAM. An
    # extractor without them builds in memory only.
    @classmethod
    def state_arrays(cls, state: Any) -> dict[str, np.ndarray]:
        raise NotImplementedError(f"extractor {cls.name!r} cannot store its sampling state")

    @classmethod
    def state_from_arrays(cls, arrays: dict[str, np.ndarray]) -> Any:
        raise NotImplementedError(f"extractor {cls.name!r} cannot store its sampling state")

    @classmethod
    def can_cache(cls) -> bool:
        """Whether features of this extractor can live in the on-disk feature cache."""
        return cls.state_arrays.__func__ is not Extractor.state_arrays.__func__


# The built-in extractors, by name -> "module:Class". Their modules are imported on first use
# (create / extractor_class), so that e.g. SIFT never imports torch, which XFeat and DISK need.
_BUILTIN: dict[str, str] = {
    "alike": "favormap.features.alike:ALIKEExtractor",
    "alike-l": "favormap.features.alike:ALIKELExtractor",
    "alike-n": "favormap.features.alike:ALIKENExtractor",
    "alike-s": "favormap.features.alike:ALIKESExtractor",
    "alike-t": "favormap.features.alike:ALIKETExtractor",
    "aliked": "favormap.features.aliked:ALIKEDExtractor",
    "disk": "favormap.features.disk:DISKExtractor",
    "sift": "favormap.features.sift:SIFTExtractor",
    "xfeat": "favormap.features.xfeat:XFeatExtractor",
}
_REGISTRY: dict[str, Callable[..., Extractor]] = {}


def register(name: str):
    """Class decorator: make an extractor available by name (it replaces a built-in of that name)."""

    def deco(cls):
        cls.name = name
        # a built-in's module imported after a user's extractor took its name leaves the user's one
        if not (_is_builtin(name, cls) and name in _REGISTRY and not _is_builtin(name, _REGISTRY[name])):
            _REGISTRY[name] = cls
        return cls

    return deco


def _is_builtin(name: str, cls) -> bool:
    return _BUILTIN.get(name) == f"{getattr(cls, '__module__', '')}:{getattr(cls, '__qualname__', '')}"


def available() -> list[str]:
    return sorted(set(_REGISTRY) | set(_BUILTIN))


def extractor_class(name: str) -> Callable[..., Extractor]:
    """The extractor registered as ``name``, importing a built-in's module on first use."""
    if name not in _REGISTRY:
        if name not in _BUILTIN:
            raise InputError(f"unknown feature extractor {name!r} (available: {', '.join(available())})")
        module, _, attr = _BUILTIN[name].partition(":")
        cls = getattr(importlib.import_module(module), attr)  # its @register fills _REGISTRY
        _REGISTRY.setdefault(name, cls)
    return _REGISTRY[name]


def create(name: str, **kwargs) -> Extractor:
    return extractor_class(name)(**kwargs)


def policy_of(name: str) -> ExtractorPolicy:
    """The policy of the extractor registered as ``name`` (:class:`ExtractorPolicy`)."""
    return extractor_class(name).policy


def check_patch(size: int, stride: int = 1, interp: bool = False) -> None:
    """ValueError unless an S x S patch can be sampled every ``stride`` pixels (patch_offsets) and,
    with ``interp``, interpolated from a sub-grid of its pixels (patch_interpolation: every pixel,
    odd S)."""
    if not (isinstance(size, (int, np.integer)) and size >= 1):
        raise ValueError(f"patch size must be an integer >= 1, not {size!r}")
    if not (isinstance(stride, (int, np.integer)) and stride >= 1):
        raise ValueError(f"patch stride must be an integer >= 1, not {stride!r}")
    if stride > 1 and (size % 2 == 0 or ((size - 1) // 2) % stride):
        raise ValueError(
            f"a patch of {size} px sampled every {stride} px must be odd with a half-width ({(size - 1) / 2:g}) "
            f"that is a multiple of the stride, so that its centre and edges are sampled"
        )
    if interp and (stride != 1 or size % 2 == 0):
        raise ValueError(
            f"an interpolated patch must have every pixel (stride 1, not {stride}) and an odd size (a centre "
            f"pixel), not {size}"
        )


def patch_offsets(size: int, stride: int = 1) -> np.ndarray:
    """(n*n, 2) pixel offsets of an S x S patch centred on 0, row-major (v, then u): every pixel
    (``stride`` 1, n = S), or every ``stride``-th pixel from the centre out to the patch's edges (an
    odd S whose half-width (S - 1) / 2 is a multiple of ``stride``, so the centre and the edges are
    kept: n = (S - 1) / stride + 1)."""
    check_patch(size, stride)
    r = (np.arange(0, size, stride) - (size - 1) / 2.0).astype(np.float32)
    vv, uu = np.meshgrid(r, r, indexing="ij")
    return np.stack([uu.ravel(), vv.ravel()], axis=1)


def patch_interpolation(size: int) -> tuple[np.ndarray, np.ndarray]:
    """The pixels of an S x S patch (every pixel, :func:`patch_offsets` order) to describe when the
    others are interpolated from them: along each axis the centre, every pixel an even distance
    from it and the edges (S = 7: offsets -3, -2, 0, 2, 3 of -3..3; each odd offset below the edge
    lies midway between two described ones). Returns the (m*m, 2) offsets to describe, row-major as
    :func:`patch_offsets`, and the (S*S, m*m) bilinear weights that give every pixel's descriptor
    from theirs (rows of the described pixels: one 1). docs/implementation-notes.md ("Features") has
    how close the interpolated descriptors come to the described ones."""
    check_patch(size, interp=True)
    h = (size - 1) // 2
    full = np.arange(size) - h
    keep = full[(full % 2 == 0) | (np.abs(full) == h)]
    w1 = np.zeros((size, len(keep)))
    for i, x in enumerate(full):  # the described pixels below and above x (x itself when described)
        j = min(int(np.searchsorted(keep, x, side="right")) - 1, max(len(keep) - 2, 0))
        t = 0.0 if len(keep) == 1 else (x - keep[j]) / (keep[j + 1] - keep[j])
        w1[i, j] = 1.0 - t
        if t:
            w1[i, j + 1] = t
    vv, uu = np.meshgrid(keep, keep, indexing="ij")
    offsets = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(np.float32)
    return offsets, np.kron(w1, w1).astype(np.float32)  # rows (v, u) row-major, as patch_offsets
