"""ops: map operations (visibility, merge, prune, export, align, extend)."""

from ..lazy import lazy_exports

_EXPORTS = {
    "AlignConfig": ".align_config",
    "AlignmentError": ".align",
    "MapAlignment": ".align",
    "align_maps": ".align",
    "MergeConfig": ".merge_config",
    "merge_maps": ".merge",
}
# lazy: importing favormap.ops does not load the map reader
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = list(_EXPORTS)
