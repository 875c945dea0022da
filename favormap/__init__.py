"""favormap: visual relocalization with persistent feature-voxel maps (FaVoR, WACV 2025)."""

__version__ = "0.1.0"

from .errors import FavormapError  # noqa: E402

__all__ = ["FavormapError", "__version__"]
