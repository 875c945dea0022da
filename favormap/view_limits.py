"""The viewing limits of a visibility query: a plain dataclass, importable without numpy (the CLI reads its
defaults from here)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class ViewLimits:
    """How far a query view may stray from the views a landmark was trained on."""

    angle_margin_deg: float = 15.0  # on top of the landmark's own training view-angle radius
    depth_scale: tuple[float, float] = (0.5, 2.0)  # allowed distance range, relative to the training range
    image_margin_px: float = 0.0  # keep landmarks projecting at least this far inside the image
