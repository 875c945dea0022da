"""The plain favormap sequence layout.

::

    SEQ/
      sequence.json
      images/...            (any image paths relative to SEQ)

``sequence.json``::

    {
      "format": "favormap-sequence", "version": 1,
      "cameras": {"0": {"model": "PINHOLE", "width": 640, "height": 480, "params": [fx, fy, cx, cy]}},
      "frames": [{"image": "images/000000.png", "camera_id": 0,
                  "cam_from_world": [[r00, r01, r02, t0], [...], [...], [0, 0, 0, 1]]}, ...]
    }

Poses are ``cam_from_world`` in OpenCV camera axes; camera models and parameters are COLMAP's.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ...errors import SequenceError
from ..types import Camera, Frame, Sequence
from .common import checked_pose, guarded

NAME = "favormap"
FILENAME = "sequence.json"
DESCRIPTOR_FILES = (FILENAME,)


def detect(root: Path) -> bool:
    return (root / FILENAME).is_file()


@guarded
def read(root: Path) -> Sequence:
    path = root / FILENAME
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise SequenceError(f"cannot parse {path}: {e}") from None
    if not isinstance(data, dict) or data.get("format") != "favormap-sequence":
        raise SequenceError(f"{path} is not a favormap sequence file (missing format: favormap-sequence)")
    try:
        cameras = {int(k): Camera.from_dict(v) for k, v in data["cameras"].items()}
        frames = []
        for i, fr in enumerate(data["frames"]):
            if "cam_from_world" not in fr:
                raise SequenceError(f"{path}: frame {i} ({fr.get('image')}) has no pose")
            T = checked_pose(fr["cam_from_world"], f"{path}: frame {i} ({fr.get('image')}) cam_from_world")
            cam_id = int(fr.get("camera_id", 0))
            if cam_id not in cameras:
                raise SequenceError(f"{path}: frame {i} refers to unknown camera {cam_id}")
            frames.append(Frame(str(fr["image"]), root / fr["image"], cam_id, T))
    except (KeyError, TypeError, ValueError) as e:
        raise SequenceError(f"{path}: malformed sequence file ({type(e).__name__}: {e})") from None
    return Sequence(root, NAME, cameras, frames)


def write(seq: Sequence, root: Path) -> Path:
    """Write ``sequence.json`` for a sequence whose images already lie under ``root``."""
    root = Path(root)
    data = {
        "format": "favormap-sequence",
        "version": 1,
        "cameras": {str(k): c.to_dict() for k, c in seq.cameras.items()},
        "frames": [
            {"image": f.name, "camera_id": f.camera_id, "cam_from_world": np.round(f.cam_from_world, 12).tolist()}
            for f in seq.frames
        ],
    }
    path = root / FILENAME
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(data, indent=1))
    tmp.replace(path)
    return path
