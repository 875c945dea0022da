"""localize: iterative render -> match -> PnP-RANSAC against a map, and its evaluation."""

from .localizer import IterationResult, LocalizationResult, LocalizeConfig, Localizer, localize, match_descriptors

__all__ = ["IterationResult", "LocalizationResult", "LocalizeConfig", "Localizer", "localize", "match_descriptors"]
