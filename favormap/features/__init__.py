"""features: keypoints + descriptors sampled anywhere, behind one small interface."""

from . import sift, xfeat  # noqa: F401  (register the built-in extractors)
from .base import Extractor, Features, available, create, patch_offsets, register

__all__ = ["Extractor", "Features", "available", "create", "patch_offsets", "register"]
