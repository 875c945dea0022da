"""localize: iterative render -> match -> PnP-RANSAC against a map, and its evaluation."""

from .config import LocalizeConfig, SuccessChecks
from .descriptors import DescriptorSource, MeanDescriptors, NearestViewDescriptors, RenderedDescriptors, make_source
from .localizer import IterationResult, LocalizationResult, Localizer, localize
from .matching import match_descriptors, match_near
from .motion import MOTION_MODELS, MotionPrior

__all__ = [
    "DescriptorSource",
    "IterationResult",
    "LocalizationResult",
    "LocalizeConfig",
    "Localizer",
    "MOTION_MODELS",
    "MeanDescriptors",
    "MotionPrior",
    "NearestViewDescriptors",
    "RenderedDescriptors",
    "SuccessChecks",
    "localize",
    "make_source",
    "match_descriptors",
    "match_near",
]
