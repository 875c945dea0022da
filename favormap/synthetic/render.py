"""Rendering the synthetic room by CPU ray casting (Open3D): one ray per (super-sampled) pixel
centre, the texture of the hit face sampled bilinearly with a fixed Lambertian-style shade; and the
pixel <-> world helpers of its cameras."""

from __future__ import annotations

import functools

import cv2
import numpy as np

from .. import geometry
from ..io.types import Camera
from .scene import Scene


def _pixel_rays(camera: Camera, cam_from_world: np.ndarray, ss: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """World rays through the centres of an ``ss`` times super-sampled pixel grid (through the lens
    distortion of a non-pinhole ``camera``).  Directions have unit z in the camera frame, so the ray
    parameter of a hit is its z-depth."""
    W, H = camera.width * ss, camera.height * ss
    T = np.asarray(cam_from_world, float)
    R = T[:3, :3].astype(np.float32)
    center = geometry.camera_centers(T)
    rays = np.empty((H, W, 2, 3), np.float32)
    rays[:, :, 0] = center.astype(np.float32)
    if not camera.has_distortion:
        fx, fy = camera.focal
        cx, cy = camera.principal_point
        xs = (((np.arange(W, dtype=np.float64) + 0.5) / ss - cx) / fx).astype(np.float32)
        ys = (((np.arange(H, dtype=np.float64) + 0.5) / ss - cy) / fy).astype(np.float32)
        # d_world = R^T d_cam = x * R[0] + y * R[1] + R[2]
        np.add((xs[:, None] * R[0] + R[2])[None], (ys[:, None] * R[1])[:, None, :], out=rays[:, :, 1])
    else:
        xy = _image_plane(camera.model, camera.width, camera.height, tuple(camera.params), ss)
        rays[:, :, 1] = (xy[:, :1] * R[0] + xy[:, 1:] * R[1] + R[2]).reshape(H, W, 3)
    return rays.reshape(-1, 6), center


def _plane_coordinates(camera: Camera, pixels: np.ndarray) -> np.ndarray:
    """(N, 2) image-plane coordinates (x, y at z = 1) of the rays of ``camera`` (any COLMAP model,
    pycolmap's unprojection) through (N, 2) pixels; NaN for rays that do not point forward (a fisheye
    sees beyond 90 degrees from its axis, a ray of z-depth 1 cannot)."""
    cam = camera.to_pycolmap()
    pixels = np.asarray(pixels, np.float64)
    ray = cam.cam_ray_from_img(pixels)
    # beyond the range where the model is invertible the unprojection is not the inverse of the
    # projection (pycolmap's fisheye models beyond 90 degrees): those pixels see nothing
    back = cam.img_from_cam(ray, check_cheirality=False)
    ok = (ray[:, 2] > 1e-6) & (np.abs(back - pixels).max(1) < 1e-3)
    return np.where(ok[:, None], ray[:, :2] / np.where(ok, ray[:, 2], 1.0)[:, None], np.nan)


@functools.lru_cache(maxsize=4)
def _image_plane(model: str, width: int, height: int, params: tuple, ss: int) -> np.ndarray:
    """Undistorted image-plane coordinates (x, y at z = 1), float32 (H*W*ss^2, 2), of the samples of
    a distorted camera (COLMAP's camera model; the same for every frame of a sequence); NaN where
    the ray does not point forward."""
    u, v = np.meshgrid((np.arange(width * ss) + 0.5) / ss, (np.arange(height * ss) + 0.5) / ss)
    cam = Camera(model, width, height, np.array(params))
    xy = _plane_coordinates(cam, np.stack([u.ravel(), v.ravel()], 1)).astype(np.float32)
    xy.flags.writeable = False
    return xy


def _cast(scene: Scene, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    ans = scene.raycaster.cast_rays(o3d.core.Tensor(rays))
    t = ans["t_hit"].numpy()
    prim = ans["primitive_ids"].numpy().astype(np.int64)
    forward = np.isfinite(rays[:, 3:]).all(1)  # rays that do not point forward (NaN) hit nothing
    t[~forward] = np.inf
    hit = np.isfinite(t)
    face = np.full(len(t), -1, np.int64)
    face[hit] = scene.tri_face[prim[hit]]
    return t, face


def render_depth(scene: Scene, camera: Camera, cam_from_world: np.ndarray) -> np.ndarray:
    """z-depth (along the optical axis) at each pixel centre, float32 HxW, inf where nothing is hit."""
    rays, _ = _pixel_rays(camera, cam_from_world, 1)
    t, _ = _cast(scene, rays)
    return t.reshape(camera.height, camera.width).astype(np.float32)


def render(
    scene: Scene, camera: Camera, cam_from_world: np.ndarray, ss: int = 2, with_depth: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Render ``scene`` seen by ``camera`` (any supported model, fisheye included: each pixel's ray is
    pycolmap's unprojection) at ``cam_from_world``; pixels whose ray does not point forward stay black.

    Returns (rgb uint8 HxWx3, depth float32 HxW): the colour is averaged over ``ss x ss`` samples
    per pixel (anti-aliasing), the depth is the z-depth at the pixel centre (COLMAP convention),
    inf where no surface is hit; None when ``with_depth`` is False.
    """
    ss = max(1, int(ss))
    W, H = camera.width * ss, camera.height * ss
    rays, center = _pixel_rays(camera, cam_from_world, ss)
    t, face = _cast(scene, rays)
    hit = face >= 0
    atlas, offsets = scene.atlas

    f = np.where(hit, face, 0)
    th = np.where(hit, t, 0).astype(np.float32)[:, None]
    p = center.astype(np.float32)[None, :] + th * rays[:, 3:]
    dp = p - scene.face_origin.astype(np.float32)[f]
    tpu = np.float32(scene.texels_per_unit)
    s_coord = np.einsum("ij,ij->i", dp, scene.face_u.astype(np.float32)[f]) * tpu
    t_coord = np.einsum("ij,ij->i", dp, scene.face_v.astype(np.float32)[f]) * tpu
    tex = scene.face_tex[f]
    tw = np.array([x.shape[1] for x in scene.textures], np.float32)[tex]
    tht = np.array([x.shape[0] for x in scene.textures], np.float32)[tex]
    # texel (c, r) covers [c, c+1) x [r, r+1); cv2.remap samples texel centres at integers
    mapx = offsets[tex, 0] + np.clip(s_coord - 0.5, -0.5, tw - 0.5)
    mapy = offsets[tex, 1] + np.clip(t_coord - 0.5, -0.5, tht - 0.5)
    mapx[~hit] = -10.0
    mapy[~hit] = -10.0
    img = cv2.remap(
        atlas,
        mapx.reshape(H, W),
        mapy.reshape(H, W),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=(0, 0, 0),
    )
    shade = np.where(hit, scene.face_shade[f], 0).astype(np.float32)
    img = img.astype(np.float32) * shade.reshape(H, W, 1)
    if ss > 1:
        img = cv2.resize(img, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    rgb = np.clip(img + 0.5, 0, 255).astype(np.uint8)

    depth = None
    if with_depth:
        if ss == 1:
            depth = t.reshape(H, W).astype(np.float32)
        else:
            depth = render_depth(scene, camera, cam_from_world)
    return rgb, depth


def surface_distance(scene: Scene, points: np.ndarray) -> np.ndarray:
    """Unsigned distance from each (N,3) point to the scene surface (Open3D compute_distance)."""
    import open3d as o3d

    pts = np.ascontiguousarray(np.atleast_2d(points), dtype=np.float32)
    return scene.raycaster.compute_distance(o3d.core.Tensor(pts)).numpy().astype(np.float64)


def backproject(camera: Camera, cam_from_world: np.ndarray, pixels: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """World points of (N,2) pixel coordinates (COLMAP convention, through the lens distortion of a
    non-pinhole ``camera``) with z-depths (N,)."""
    pixels = np.atleast_2d(np.asarray(pixels, float))
    z = np.asarray(depth, float).reshape(-1)
    if not camera.has_distortion:
        xy = geometry.unproject(camera.K, pixels)[:, :2]
    else:
        xy = _plane_coordinates(camera, pixels)
    return geometry.transform_points(geometry.inverse(cam_from_world), np.c_[xy * z[:, None], z])


def project(camera: Camera, cam_from_world: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,2) pixel coordinates (COLMAP convention, through the lens distortion of a non-pinhole
    ``camera``) and (N,) z-depths of world points."""
    uv, z = geometry.project(camera.K, cam_from_world, np.atleast_2d(points), with_depth=True)
    if camera.has_distortion:
        Xc = geometry.transform_points(np.asarray(cam_from_world, float), np.atleast_2d(points).astype(float))
        uv = camera.to_pycolmap().img_from_cam(Xc, check_cheirality=False)
    return uv, z
