"""Sequence readers. Each module defines ``NAME``, ``detect(root) -> bool`` and
``read(root) -> Sequence`` (and optionally ``DESCRIPTOR_FILES``, glob patterns of the files a user
may give instead of the folder); register new ones in ``READERS`` (detection order)."""

from __future__ import annotations

import importlib

# module names, tried in this order by auto-detection
_MODULES = ["favormap_layout", "nerf", "colmap", "sevenscenes_flat", "sevenscenes", "cambridge", "tum", "llff"]


def _load():
    readers = {}
    for m in _MODULES:
        try:
            mod = importlib.import_module(f"{__name__}.{m}")
        except ModuleNotFoundError as e:  # reader not written yet
            if e.name and e.name.endswith(m):
                continue
            raise
        readers[mod.NAME] = mod
    return readers


READERS = _load()
