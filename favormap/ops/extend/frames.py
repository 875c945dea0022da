"""The extended map's frames: the map's, then the new sequence's."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Frames:
    """The frames of the extended map (:func:`output_frames`): the map's, then the new ones."""

    cameras: dict  # camera id -> Camera, equal cameras shared
    names: list[str]  # new names that collide prefixed ``+N/``
    camera_ids: np.ndarray  # (M,) int32
    cam_from_world: np.ndarray  # (M, 4, 4) float64
    Ks: np.ndarray  # (M, 3, 3) intrinsics of the working images (the map's max_side)


def output_frames(m, seq, ff) -> Frames:
    """The frames of the map ``m`` followed by those of ``seq`` (features ``ff``): cameras (equal cameras
    shared), frame names (new names that collide prefixed ``+N/``), camera ids, poses and intrinsics."""
    from ...io import working_camera
    from ..merge import _camera_id

    cameras = dict(m.cameras)
    new_ids = {cid: _camera_id(cameras, cam) for cid, cam in seq.cameras.items()}
    names = list(m.frame_names)
    seen = set(names)
    for fr in seq.frames:
        name, k = fr.name, 1
        while name in seen:
            name, k = f"+{k}/{fr.name}", k + 1
        seen.add(name)
        names.append(name)
    cam_ids = np.concatenate([np.asarray(m.frame_camera_ids, np.int32), [new_ids[f.camera_id] for f in seq.frames]])
    poses = np.concatenate([np.asarray(m.cam_from_world, np.float64), np.stack([f.cam_from_world for f in seq.frames])])
    Ks_old = {cid: working_camera(cam, m.max_side).K for cid, cam in m.cameras.items()}
    Ks = np.concatenate([np.stack([Ks_old[int(c)] for c in m.frame_camera_ids]), np.stack([c.K for c in ff.cameras])])
    return Frames(cameras, names, cam_ids.astype(np.int32), poses, Ks)


def frames_in_map(m, seq) -> list[str]:
    """Names of the frames of ``seq`` that the map ``m`` holds already: the same name and the same pose."""
    index = {name: i for i, name in enumerate(m.frame_names)}
    poses = np.asarray(m.cam_from_world, np.float64)
    return [
        f.name
        for f in seq.frames
        if f.name in index and np.allclose(poses[index[f.name]], f.cam_from_world, rtol=1e-5, atol=1e-6)
    ]
