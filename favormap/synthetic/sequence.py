"""Rendered sequences of the synthetic room on disk, in the plain favormap layout."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..io.types import Camera, Frame, Sequence
from .paths import camera_path, make_camera
from .render import render
from .scene import Scene, make_room


def write_sequence(
    root,
    n_frames: int = 30,
    width: int = 640,
    height: int = 480,
    fov_deg: float = 60.0,
    seed: int = 0,
    path: str = "orbit",
    depth: bool = False,
    ss: int = 2,
    poses=None,
    scene: Scene | None = None,
    step: float = 0.07,
    camera: Camera | None = None,
) -> Sequence:
    """Render a posed sequence of the room into ``root`` in the plain favormap layout:
    ``root/images/000000.png ...`` and ``root/sequence.json`` (one PINHOLE camera, id 0); with
    ``depth``, also ``root/depth/000000.npy ...`` (float32 z-depth, inf where nothing is hit).

    ``poses`` overrides the path (e.g. query views from :func:`random_views_near`); ``scene``
    overrides ``make_room(seed)``; ``camera`` (any supported model: the images show its lens
    distortion) overrides the PINHOLE camera of ``width``, ``height`` and ``fov_deg``.  Returns the
    Sequence (``extra["synthetic"]`` notes the
    settings; ``extra["depth"]`` lists the depth files when written)."""
    from ..io.readers import favormap_layout

    root = Path(root)
    scene = scene if scene is not None else make_room(seed)
    custom = poses is not None
    if not custom:
        poses = camera_path(n_frames, kind=path, seed=seed, step=step)
    poses = [np.asarray(p, float) for p in poses]
    camera = make_camera(width, height, fov_deg) if camera is None else camera
    (root / "images").mkdir(parents=True, exist_ok=True)
    if depth:
        (root / "depth").mkdir(parents=True, exist_ok=True)
    frames, depth_files = [], []
    for i, T in enumerate(poses):
        rgb, d = render(scene, camera, T, ss=ss, with_depth=depth)
        name = f"images/{i:06d}.png"
        if not cv2.imwrite(str(root / name), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise OSError(f"cannot write {root / name}")
        if depth:
            dname = f"depth/{i:06d}.npy"
            np.save(root / dname, d)
            depth_files.append(dname)
        frames.append(Frame(name, root / name, 0, T))
    extra = {
        "synthetic": {
            "scene": "room",
            "seed": int(seed),
            "path": "custom" if custom else path,
            "fov_deg": float(fov_deg),
            "ss": int(ss),
        }
    }
    if depth:
        extra["depth"] = depth_files
    seq = Sequence(root, favormap_layout.NAME, {0: camera}, frames, extra)
    favormap_layout.write(seq, root)
    return seq
