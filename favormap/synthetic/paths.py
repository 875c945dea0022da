"""Cameras and camera paths in the synthetic room: smooth loops for mapping, held-out views near them."""

from __future__ import annotations

import numpy as np

from .. import geometry
from ..io.types import Camera
from .scene import UP, Scene


def make_camera(width: int = 640, height: int = 480, fov_deg: float = 60.0) -> Camera:
    """A PINHOLE camera with horizontal field of view ``fov_deg`` and a centred principal point."""
    f = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    return Camera("PINHOLE", int(width), int(height), [f, f, width / 2.0, height / 2.0])


def _smooth_jitter(rng: np.random.Generator, dims: int, amp: float):
    """A smooth random function of arc length s (sum of a few sinusoids), returns s -> (len(s), dims)."""
    k = 3
    lam = rng.uniform(0.6, 2.5, (k, dims))
    ph = rng.uniform(0, 2 * np.pi, (k, dims))
    a = rng.uniform(0.3, 1.0, (k, dims))
    a *= amp / a.sum(axis=0)

    def f(s):
        s = np.asarray(s, float)[:, None, None]
        return np.sum(a * np.sin(2 * np.pi * s / lam + ph), axis=1)

    return f


def _loop(kind: str, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres and look-at targets of a closed loop, parameterised by phi (2 pi periodic)."""
    if kind == "orbit":
        # arc around the box cluster: out along an outer lane, back along an inner, lower lane
        c = np.array([0.0, 0.55, 0.8])
        alpha = np.radians(50) * np.sin(phi)
        r = 1.68 + 0.1 * np.cos(phi)
        eye = np.stack([c[0] + r * np.sin(alpha), c[1] - r * np.cos(alpha), 1.4 + 0.18 * np.cos(phi)], axis=1)
        target = np.tile(c, (len(phi), 1))
        target[:, 0] += 0.25 * np.sin(alpha)
        return eye, target
    if kind == "walk":
        # lateral walk facing the far wall, with a little forward/backward and up/down motion
        x = 1.25 * np.sin(phi)
        eye = np.stack([x, -0.85 + 0.2 * np.cos(phi), 1.5 + 0.1 * np.sin(2 * phi)], axis=1)
        target = np.stack([0.6 * x + 0.2 * np.cos(phi), np.full_like(x, 1.5), 0.95 + 0.1 * np.cos(phi)], axis=1)
        return eye, target
    raise ValueError(f"unknown camera path kind {kind!r} (use 'orbit' or 'walk')")


def _roll(cam_from_world: np.ndarray, angle_rad: float) -> np.ndarray:
    Rz = np.eye(4)
    Rz[:3, :3] = geometry.rotation_about([0.0, 0.0, 1.0], angle_rad)
    return Rz @ cam_from_world


def camera_path(n: int, kind: str = "orbit", seed: int = 0, step: float = 0.07) -> list[np.ndarray]:
    """``n`` cam_from_world poses along a smooth closed path inside the room made by
    :func:`make_room`, ``step`` units apart (uniform in arc length), looking at the room content
    with a small smooth look-at and roll jitter.  Consecutive frames overlap strongly (a few
    degrees of rotation per frame), so features can be followed through many frames.
    ``kind``: "orbit" (an arc ~1.7 units around the boxes) or "walk" (a lateral walk ~2.3 units
    from the far wall)."""
    rng = np.random.default_rng([int(seed), 7])
    phi0 = -np.pi / 2 + rng.uniform(-0.3, 0.3)
    dense = np.linspace(0, 2 * np.pi, 4001)
    eye, _ = _loop(kind, phi0 + dense)
    seg = np.linalg.norm(np.diff(eye, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    loop_len = cum[-1]
    s = np.arange(n) * float(step)
    phi = phi0 + 2 * np.pi * np.floor(s / loop_len) + np.interp(s % loop_len, cum, dense)
    eye, target = _loop(kind, phi)
    target = target + _smooth_jitter(rng, 3, 0.06)(s)
    roll = _smooth_jitter(rng, 1, np.radians(2.5))(s)[:, 0]
    return [_roll(geometry.look_at(e, t, up=UP), r) for e, t, r in zip(eye, target, roll)]


def random_views_near(
    poses, n: int, seed: int = 0, max_trans: float = 0.1, max_rot_deg: float = 5.0, scene: Scene | None = None
) -> list[np.ndarray]:
    """``n`` held-out poses near a path: each interpolates two consecutive ``poses`` at a random
    fraction (centre linearly, rotation by slerp), then moves by up to ``max_trans`` units and
    rotates by up to ``max_rot_deg`` degrees in random directions.  With ``scene``, poses whose
    centre is not safely inside the room (see :meth:`Scene.camera_is_valid`) are redrawn."""
    poses = [np.asarray(p, float) for p in poses]
    if not poses:
        raise ValueError("random_views_near needs at least one pose")
    rng = np.random.default_rng([int(seed), 11])
    out = []
    tries = 0
    while len(out) < n:
        tries += 1
        if tries > 1000 * max(1, n):
            raise RuntimeError("could not place valid views near the given poses")
        i = int(rng.integers(0, max(1, len(poses) - 1)))
        j = min(i + 1, len(poses) - 1)
        w = float(rng.uniform(0, 1))
        A, B = geometry.inverse(poses[i]), geometry.inverse(poses[j])
        wfc = np.eye(4)
        wfc[:3, :3] = geometry.slerp(A[:3, :3], B[:3, :3], w)
        wfc[:3, 3] = (1 - w) * A[:3, 3] + w * B[:3, 3]
        T = geometry.perturb_pose(
            geometry.inverse(wfc), float(rng.uniform(0, max_trans)), float(rng.uniform(0, max_rot_deg)), rng
        )
        if scene is not None and not scene.camera_is_valid(geometry.camera_centers(T)):
            continue
        out.append(T)
    return out
