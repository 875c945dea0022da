"""synthetic: an exactly posed, textured room rendered by CPU ray casting, for tests and demos."""

from .paths import camera_path, make_camera, random_views_near
from .render import backproject, project, render, render_depth, surface_distance
from .scene import Box, Scene, make_room
from .sequence import write_sequence
from .texture import make_texture

__all__ = [
    "Box",
    "Scene",
    "backproject",
    "camera_path",
    "make_camera",
    "make_room",
    "make_texture",
    "project",
    "random_views_near",
    "render",
    "render_depth",
    "surface_distance",
    "write_sequence",
]
