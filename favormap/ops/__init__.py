"""ops: map operations (visibility, merge, prune, export, align)."""

_ALIGN = ("AlignConfig", "AlignmentError", "MapAlignment", "align_maps")


def __getattr__(name):  # lazy: importing favormap.ops does not load the map reader
    if name in _ALIGN:
        from . import align

        return getattr(align, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = list(_ALIGN)
