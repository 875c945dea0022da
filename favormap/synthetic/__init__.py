"""synthetic: an exactly posed, textured room rendered by CPU ray casting, for tests and demos."""

from .scene import (
    Box,
    Scene,
    backproject,
    camera_path,
    make_camera,
    make_room,
    make_texture,
    project,
    random_views_near,
    render,
    render_depth,
    surface_distance,
    write_sequence,
)

__all__ = ["Box", "Scene", "backproject", "camera_path", "make_camera", "make_room", "make_texture", "project",
           "random_views_near", "render", "render_depth", "surface_distance", "write_sequence"]
