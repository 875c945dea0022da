"""localize: iterative render -> match -> PnP-RANSAC against a map, and its evaluation.

The stage modules are imported on first use (PEP 562 ``__getattr__``), so that ``favormap.localize.config``
-- the settings, which the CLI reads its defaults from -- imports no numpy."""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..lazy import lazy_exports

if TYPE_CHECKING:
    from .config import LocalizeConfig, SuccessChecks
    from .descriptors import DescriptorSource, MeanDescriptors, NearestViewDescriptors, RenderedDescriptors, make_source
    from .localizer import IterationResult, LocalizationResult, Localizer, localize
    from .matching import match_descriptors, match_near
    from .motion import MOTION_MODELS, MotionPrior

_LAZY = {
    "LocalizeConfig": ".config",
    "SuccessChecks": ".config",
    "DescriptorSource": ".descriptors",
    "MeanDescriptors": ".descriptors",
    "NearestViewDescriptors": ".descriptors",
    "RenderedDescriptors": ".descriptors",
    "make_source": ".descriptors",
    "IterationResult": ".localizer",
    "LocalizationResult": ".localizer",
    "Localizer": ".localizer",
    "localize": ".localizer",
    "match_descriptors": ".matching",
    "match_near": ".matching",
    "MOTION_MODELS": ".motion",
    "MotionPrior": ".motion",
}

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


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)
