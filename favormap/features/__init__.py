"""features: keypoints + descriptors sampled anywhere, behind one small interface."""

from . import disk, sift, xfeat  # noqa: F401  (register the built-in extractors; disk's packages load on use)
from .base import Extractor, Features, available, create, patch_offsets, register

__all__ = ["Extractor", "Features", "available", "create", "patch_offsets", "register"]
