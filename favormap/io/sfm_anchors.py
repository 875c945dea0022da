"""Anchor poses: the known poses of a few of the images that structure from motion poses, which put its
reconstruction into their world frame and units (metres, for poses from GPS/RTK, motion capture or a survey).

The similarity (scale, rotation, translation) that maps the reconstruction's camera centres onto the anchors'
given centres is fitted by least squares (Umeyama) over the anchors that registered, and applied to the whole
reconstruction. Three anchors at least, not on one line, fix it. Its residuals tell how well the given poses
and the reconstruction agree: the centres' distances after the fit (RMS and max, in the anchors' units) and
the angle between each anchor's given orientation and its camera's after the fit (median, degrees).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import PurePath

import numpy as np

from ..errors import InputError
from ..geometry import camera_centers, from_rigid3d, rotation_angle_deg, umeyama

MIN_ANCHORS = 3
# the anchors' centres, centred, must spread across a plane: their second singular value at least this share of
# the first (on one line the rotation about that line is free)
MIN_SPREAD = 0.05


@dataclass
class AnchorFit:
    """The similarity that took a reconstruction into the anchors' frame and how well it fits."""

    used: list[str]  # the anchors' images that registered, which the similarity fits
    missing: list[str] = field(default_factory=list)  # anchors naming no image given to the estimation
    unregistered: list[str] = field(default_factory=list)  # anchors' images that did not register
    world_from_reconstruction: np.ndarray = field(default_factory=lambda: np.eye(4))  # 4x4 similarity
    scale: float = 1.0
    rms: float = 0.0  # the centres' residuals after the fit, in the anchors' units
    max: float = 0.0
    rotation_median_deg: float = 0.0

    def to_dict(self) -> dict:
        return {
            "anchors": len(self.used),
            "used": list(self.used),
            "missing": list(self.missing),
            "unregistered": list(self.unregistered),
            "scale": float(self.scale),
            "residual_rms": round(float(self.rms), 6),
            "residual_max": round(float(self.max), 6),
            "rotation_median_deg": round(float(self.rotation_median_deg), 4),
        }


def match_anchors(anchors: dict, names: list[str]) -> tuple[dict, list[str]]:
    """({image name: cam_from_world}, the anchors' names that name none of ``names``): an anchor names an
    image by its name or its name without the extension."""
    by_key = {}
    for n in names:
        by_key.setdefault(n, n)
        by_key.setdefault(PurePath(n).stem, n)
    found, missing = {}, []
    for key, pose in anchors.items():
        if key in by_key:
            found[by_key[key]] = np.asarray(pose, np.float64)
        else:
            missing.append(key)
    return found, missing


def _check(centers: np.ndarray, names: list[str], what: str, lost: str) -> None:
    if len(names) < MIN_ANCHORS:
        raise InputError(
            f"the anchor poses need {MIN_ANCHORS} images at least{' ' * bool(what)}{what}, found {len(names)}"
            + (f" ({', '.join(names)})" if names else "")
            + lost
        )
    sv = np.linalg.svd(centers - centers.mean(0), compute_uv=False)
    if not sv[0] > 0 or sv[1] < MIN_SPREAD * sv[0]:
        raise InputError(
            f"the anchor poses' camera centres{' ' * bool(what)}{what} lie on one line (or one point): they leave "
            f"the rotation about it free; give anchors spread across a plane ({', '.join(names)})"
        )


def check_anchors(anchors: dict, names: list[str]) -> tuple[dict, list[str]]:
    """:func:`match_anchors`, refused (InputError) unless 3 anchors or more name images and their centres
    are not collinear: before the estimation, whose result they could not anchor."""
    found, missing = match_anchors(anchors, names)
    lost = f"; naming no image: {', '.join(missing)}" if missing else ""
    _check(camera_centers(np.stack(list(found.values()))) if found else np.zeros((0, 3)), list(found), "", lost)
    return found, missing


def anchor_reconstruction(rec, anchors: dict, missing: list[str] | None = None) -> AnchorFit:
    """Move the pycolmap Reconstruction ``rec`` into the frame of ``anchors`` ({image name: cam_from_world}):
    the similarity fitted to the centres of the anchors' images that registered. InputError when fewer than 3
    of them registered or their centres are collinear (``rec`` then unchanged)."""
    import pycolmap

    posed = {im.name: im for im in rec.images.values() if im.has_pose}
    used = [n for n in anchors if n in posed]
    unregistered = [n for n in anchors if n not in posed]
    given = np.stack([anchors[n] for n in used]) if used else np.zeros((0, 4, 4))
    lost = f"; not registered: {', '.join(unregistered)}" if unregistered else ""
    _check(camera_centers(given), used, "that registered", lost)
    estimated = np.stack([from_rigid3d(posed[n].cam_from_world()) for n in used])
    src = camera_centers(estimated)
    _check(src, used, "that registered (as reconstructed)", lost)
    S = umeyama(src, camera_centers(given))
    s = float(np.cbrt(np.linalg.det(S[:3, :3])))
    rec.transform(pycolmap.Sim3d(s, pycolmap.Rotation3d(S[:3, :3] / s), S[:3, 3]))
    moved = np.stack([from_rigid3d(rec.images[posed[n].image_id].cam_from_world()) for n in used])
    residual = np.linalg.norm(camera_centers(moved) - camera_centers(given), axis=1)
    turn = rotation_angle_deg(np.einsum("nij,nkj->nik", moved[:, :3, :3], given[:, :3, :3]))
    return AnchorFit(
        used=used,
        missing=list(missing or []),
        unregistered=unregistered,
        world_from_reconstruction=S,
        scale=s,
        rms=float(np.sqrt(np.mean(residual**2))),
        max=float(residual.max()),
        rotation_median_deg=float(np.median(turn)),
    )
