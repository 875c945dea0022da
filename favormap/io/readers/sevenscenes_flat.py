"""7-Scenes as tsdf-fusion ships it: one flat folder with a ``camera-intrinsics.txt``.

::

    ROOT/
      camera-intrinsics.txt          3x3 K (9 numbers, whitespace separated)
      frame-000000.color.jpg         (or .png)
      frame-000000.pose.txt          4x4 camera-to-world (world_from_cam), OpenCV camera axes
      ...

Frames, poses and the inf/nan rule are those of the ``7scenes`` reader (favormap.io.readers.sevenscenes).

Focal length: the 585 px that 7-Scenes publishes (and that this file holds) belongs to the Kinect's
depth camera; DSAC*, ACE and hloc use 525 px for the RGB images. When the file holds the published
depth value (585 px at 640x480, or that value scaled to the image size), the RGB focal
``FOCAL_POLICY`` chooses is used instead; any other K is taken as given. Which focal a read used is
logged in one line and kept in ``Sequence.extra["focal"]``.
"""

from __future__ import annotations

import logging
from pathlib import Path

from ..types import Sequence
from . import sevenscenes
from .common import guarded, image_size, make_camera

NAME = "7scenes-flat"
INTRINSICS_FILE = "camera-intrinsics.txt"
DEPTH_FOCAL_PX = 585.0  # the published 7-Scenes focal (640x480): the depth camera's
RGB_FOCAL_PX = 525.0  # the RGB focal that DSAC*, ACE and hloc use (640x480)
# "file": the focal in camera-intrinsics.txt; "rgb": RGB_FOCAL_PX where the file holds the depth focal. The
# RGB focal is the default: the tracks fit the poses better with it and more queries localize
# (docs/accuracy.md, "7-Scenes focal length")
FOCAL_POLICY = "rgb"
log = logging.getLogger(__name__)


def detect(root: Path) -> bool:
    root = Path(root)
    return (root / INTRINSICS_FILE).is_file() and next(root.glob("frame-*.pose.txt"), None) is not None


def _holds_depth_focal(fx: float, fy: float, width: int) -> bool:
    published = DEPTH_FOCAL_PX * width / 640.0
    return abs(fx - published) < 0.5 and abs(fy - published) < 0.5


def read_with_focal(root: Path, policy: str) -> Sequence:
    """The sequence with the focal of ``policy`` ("file" or "rgb"; see the module docstring)."""
    if policy not in ("file", "rgb"):
        raise ValueError(f"focal policy must be 'file' or 'rgb', got {policy!r}")
    root = Path(root)
    seq = sevenscenes.read(root)  # frames and poses; its camera is replaced below
    cam_file = root / INTRINSICS_FILE
    size = image_size(seq.frames[0].image_path)
    cam = sevenscenes._read_K_file(cam_file, size)
    fx, fy = cam.focal
    cx, cy = cam.principal_point
    source = f"{INTRINSICS_FILE}"
    if policy == "rgb" and _holds_depth_focal(fx, fy, size[0]):
        fx = fy = RGB_FOCAL_PX * size[0] / 640.0
        source = f"the 7-Scenes RGB focal ({INTRINSICS_FILE} holds the depth camera's {DEPTH_FOCAL_PX:g} px)"
        cam = make_camera("PINHOLE", size[0], size[1], [fx, fy, cx, cy], str(cam_file))
    log.info("7scenes: focal %g x %g px from %s", fx, fy, source)
    extra = dict(seq.extra, focal={"fx": fx, "fy": fy, "source": source})
    return Sequence(root, NAME, {0: cam}, seq.frames, extra)


@guarded
def read(root: Path) -> Sequence:
    return read_with_focal(root, FOCAL_POLICY)
