"""The one place where poses are converted.

Conventions (pycolmap's):
- a pose is a 4x4 rigid transform as a float64 numpy array;
- ``cam_from_world`` maps world points into the camera frame, ``world_from_cam`` is its inverse;
- camera axes are OpenCV's: x right, y down, z forward;
- pixel coordinates follow COLMAP: the centre of the top-left pixel is (0.5, 0.5).
"""

from __future__ import annotations

import numpy as np

# OpenGL / NeRF camera axes (x right, y up, z backward) -> OpenCV axes.
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of one rigid transform (4x4) or a batch (...,4,4)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def world_from_cam_opengl_to_opencv(world_from_cam_gl: np.ndarray) -> np.ndarray:
    """NeRF/instant-ngp/LLFF camera-to-world (OpenGL axes) -> world_from_cam (OpenCV axes)."""
    return np.asarray(world_from_cam_gl, dtype=np.float64) @ _GL_TO_CV


def world_from_cam_opencv_to_opengl(world_from_cam_cv: np.ndarray) -> np.ndarray:
    """world_from_cam (OpenCV axes) -> NeRF/instant-ngp camera-to-world (OpenGL axes)."""
    return np.asarray(world_from_cam_cv, dtype=np.float64) @ _GL_TO_CV


def world_from_cam_llff_to_opencv(pose_3x4: np.ndarray) -> np.ndarray:
    """LLFF ``poses_bounds.npy`` pose(s) (...,3,>=4; rotation columns [down, right, backwards],
    4th column the camera centre) -> world_from_cam (...,4,4) in OpenCV axes [right, down, forward]."""
    P = np.asarray(pose_3x4, dtype=np.float64)
    T = np.zeros(P.shape[:-2] + (4, 4))
    T[..., :3, 0] = P[..., :3, 1]
    T[..., :3, 1] = P[..., :3, 0]
    T[..., :3, 2] = -P[..., :3, 2]
    T[..., :3, 3] = P[..., :3, 3]
    T[..., 3, 3] = 1.0
    return T


def cam_from_world_from_center(R_cam_from_world: np.ndarray, center: np.ndarray) -> np.ndarray:
    """cam_from_world from its rotation and the camera centre in world coordinates (t = -R c)."""
    R = np.asarray(R_cam_from_world, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ np.asarray(center, dtype=np.float64)
    return T


# The one tolerance for rotations read from files (poses, priors, transforms): the largest entry of
# |R^T R - I|. Real captures carry rounding (7-Scenes pose files ~2e-4, TUM's 4-decimal quaternions
# ~4e-4); anything within it is projected onto SO(3) at read time, anything beyond is refused.
ROTATION_TOL = 1e-3


def rotation_deviation(R: np.ndarray) -> float:
    """How far a 3x3 matrix is from a rotation: max |R^T R - I| (inf for det <= 0 or non-finite)."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)) or np.linalg.det(R) <= 0:
        return float("inf")
    return float(np.abs(R.T @ R - np.eye(3)).max())


def quaternion_deviation(q) -> float:
    """:func:`rotation_deviation` of the matrix a quaternion stands for before normalisation (the
    homogeneous formula gives |q|^2 R, so the deviation is | |q|^4 - 1 |); inf for a zero quaternion."""
    n = float(np.linalg.norm(np.asarray(q, dtype=np.float64)))
    return abs(n**4 - 1) if np.isfinite(n) and n > 1e-12 else float("inf")


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """The rotation matrix closest to ``R`` (Frobenius norm; SVD projection onto SO(3))."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    D = np.diag([1.0, 1.0, np.linalg.det(U @ Vt)])
    return U @ D @ Vt


def is_rigid(T: np.ndarray, tol: float = ROTATION_TOL) -> bool:
    """True for a finite 4x4 (or 3x4) matrix whose rotation block is orthonormal with det +1."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape not in ((4, 4), (3, 4)) or not np.all(np.isfinite(T)):
        return False
    if T.shape == (4, 4) and not np.allclose(T[3], [0, 0, 0, 1], atol=tol):
        return False
    R = T[:3, :3]
    return bool(np.allclose(R.T @ R, np.eye(3), atol=tol) and abs(np.linalg.det(R) - 1) < tol)


def camera_centers(cam_from_world: np.ndarray) -> np.ndarray:
    """Camera centres in world coordinates, (...,3)."""
    R = cam_from_world[..., :3, :3]
    t = cam_from_world[..., :3, 3]
    return -np.einsum("...ji,...j->...i", R, t)


def move_poses(cam_from_world: np.ndarray, new_from_old: np.ndarray) -> np.ndarray:
    """Poses ``cam_from_world`` (..., 4, 4) of an old world frame in a new one, ``new_from_old`` a similarity
    (x_new = s R x_old + t): ``cam_from_world @ new_from_old^-1`` with its top rows scaled by s, so that the
    poses stay rigid and the cameras keep the new frame's units."""
    T = np.asarray(new_from_old, np.float64)
    P = np.asarray(cam_from_world, np.float64) @ np.linalg.inv(T)
    P[..., :3, :] *= float(np.cbrt(np.linalg.det(T[:3, :3])))
    return P


def umeyama(src: np.ndarray, dst: np.ndarray, weights=None) -> np.ndarray:
    """Batched similarity fits: ``src``, ``dst`` (..., N, 3) -> (..., 4, 4) T with dst ~ T src
    (Umeyama 1991, least squares over the N pairs)."""
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    mu_s = src.mean(-2, keepdims=True)
    mu_d = dst.mean(-2, keepdims=True)
    xs, xd = src - mu_s, dst - mu_d
    n = src.shape[-2]
    C = np.swapaxes(xd, -1, -2) @ xs / n  # (..., 3, 3)
    U, S, Vt = np.linalg.svd(C)
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    D = np.ones(S.shape)
    D[..., 2] = d
    R = (U * D[..., None, :]) @ Vt
    var_s = np.sum(xs**2, axis=(-1, -2)) / n
    s = np.sum(S * D, -1) / np.maximum(var_s, 1e-300)
    T = np.zeros((*src.shape[:-2], 4, 4))
    T[..., :3, :3] = s[..., None, None] * R
    T[..., :3, 3] = mu_d[..., 0, :] - (s[..., None, None] * R @ mu_s[..., 0, :, None])[..., 0]
    T[..., 3, 3] = 1
    return T


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply one 4x4 transform to (N,3) points."""
    return points @ T[:3, :3].T + T[:3, 3]


def quat_to_rotmat(q_xyzw: np.ndarray) -> np.ndarray:
    """Quaternion(s) (x, y, z, w), normalised here -> rotation matrix(es) (...,3,3). (NumPy: the
    localization path imports no scipy.)"""
    q = np.asarray(q_xyzw, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    R = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )  # fmt: skip
    return R.reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion (x, y, z, w) with w >= 0 (Shepperd's method: the
    largest of the four diagonal combinations sets the well-conditioned component)."""
    m = np.asarray(R, dtype=np.float64).reshape(3, 3)
    tr = np.trace(m)
    cand = np.array([tr, m[0, 0], m[1, 1], m[2, 2]])
    k = int(np.argmax(cand))
    if k == 0:
        r = np.sqrt(1.0 + tr) * 2
        q = [(m[2, 1] - m[1, 2]) / r, (m[0, 2] - m[2, 0]) / r, (m[1, 0] - m[0, 1]) / r, 0.25 * r]
    elif k == 1:
        r = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [0.25 * r, (m[0, 1] + m[1, 0]) / r, (m[0, 2] + m[2, 0]) / r, (m[2, 1] - m[1, 2]) / r]
    elif k == 2:
        r = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 1] + m[1, 0]) / r, 0.25 * r, (m[1, 2] + m[2, 1]) / r, (m[0, 2] - m[2, 0]) / r]
    else:
        r = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[0, 2] + m[2, 0]) / r, (m[1, 2] + m[2, 1]) / r, 0.25 * r, (m[1, 0] - m[0, 1]) / r]
    q = np.asarray(q) / np.linalg.norm(q)
    return q if q[3] >= 0 else -q


def pose_from_quat_t(q_xyzw, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = quat_to_rotmat(q_xyzw)
    T[:3, 3] = t
    return T


def rotation_about(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotation matrix of ``angle_rad`` about ``axis`` (right-handed)."""
    axis = np.asarray(axis, dtype=np.float64)
    return rotvec_to_rotmat(axis / np.linalg.norm(axis) * float(angle_rad))


def rotvec_to_rotmat(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (axis times angle in radians; zero: the identity), by
    Rodrigues' formula (NumPy: the localizer, which refines poses with it, imports no scipy.spatial)."""
    w = np.asarray(rotvec, dtype=np.float64).reshape(3)
    theta = float(np.linalg.norm(w))
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-12:
        return np.eye(3) + K
    K /= theta
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * (K @ K)


def slerp(R0: np.ndarray, R1: np.ndarray, w: float) -> np.ndarray:
    """The rotation a fraction ``w`` of the way from ``R0`` to ``R1`` along the shorter arc."""
    from scipy.spatial.transform import Rotation, Slerp  # lazy: map-reading commands import no scipy

    return Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([R0, R1])))([float(w)]).as_matrix()[0]


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """cam_from_world of an OpenCV camera at ``eye`` looking at ``target`` (``up`` = image-up hint,
    given as the world direction that should point up in the image)."""
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    down = -np.asarray(up, float)
    x = np.cross(down, z)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(np.array([1.0, 0, 0]), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ eye
    return T


def plane_points(
    K: np.ndarray, cam_from_world: np.ndarray, pix: np.ndarray, X: np.ndarray, n: np.ndarray
) -> np.ndarray:
    """Where the rays of pixels ``pix`` (N, G, 2) of the pinhole camera (K, cam_from_world) meet the
    planes through the points X (N, 3) with normals n (N, 3): (N, G, 3), world. A landmark's local
    plane carries a neighbourhood of pixels from one view into another (favormap.triangulation,
    favormap.localize.align)."""
    T = np.asarray(cam_from_world, np.float64)
    R, C = T[:3, :3], camera_centers(T)
    h = np.concatenate([pix, np.ones(pix.shape[:-1] + (1,))], -1)
    rays = np.einsum("ij,ngj->ngi", R.T @ np.linalg.inv(K), h)
    lam = np.einsum("ni,ni->n", n, X - C)[:, None] / np.einsum("ni,ngi->ng", n, rays)
    return C + lam[..., None] * rays


def plane_homographies(
    K_a: np.ndarray, T_a: np.ndarray, K_b: np.ndarray, T_b: np.ndarray, X: np.ndarray, n: np.ndarray
) -> np.ndarray:
    """(N, 3, 3) homographies carrying pixels of camera a (K_a (N,3,3), cam_from_world T_a (N,4,4)) through the
    planes through X (N, 3) with normals n (N, 3) into camera b: :func:`plane_points` followed by
    :func:`project` in one product, K_b [R_b (C_a n^T + c I) + t_b n^T] R_a^T K_a^-1 with c = n . (X - C_a)."""
    T_a, T_b = np.asarray(T_a, np.float64), np.asarray(T_b, np.float64)
    Ca = camera_centers(T_a)
    c = np.einsum("ni,ni->n", n, X - Ca)
    Rb = T_b[:, :3, :3]
    inner = np.einsum("nij,nj,nk->nik", Rb, Ca, n) + c[:, None, None] * Rb + T_b[:, :3, 3][:, :, None] * n[:, None, :]
    return np.asarray(K_b, np.float64) @ inner @ np.transpose(T_a[:, :3, :3], (0, 2, 1)) @ np.linalg.inv(K_a)


def apply_homographies(H: np.ndarray, pix: np.ndarray) -> np.ndarray:
    """Pixels ``pix`` (N, G, 2) carried by the homographies ``H`` (N, 3, 3), one per row: (N, G, 2)."""
    x, y = pix[..., 0], pix[..., 1]
    q = [H[:, i, 0, None] * x + H[:, i, 1, None] * y + H[:, i, 2, None] for i in range(3)]
    w = np.where(np.abs(q[2]) < 1e-12, 1e-12, q[2])
    return np.stack([q[0] / w, q[1] / w], -1)


def project(K: np.ndarray, cam_from_world: np.ndarray, points: np.ndarray, with_depth: bool = False):
    """Pixel positions (N, 2) of world points (N, 3) in a pinhole camera with intrinsics ``K`` (COLMAP
    pixel convention when K is a COLMAP/favormap camera's): the one pinhole projection of favormap.
    ``K`` (3,3) and ``cam_from_world`` (4,4) may also be given per point, (N,3,3) and (N,4,4).
    With ``with_depth`` also the z-depths (N,): points at depth <= 0 are behind the camera and get
    meaningless pixels (depth 0 is guarded against division only)."""
    T = np.asarray(cam_from_world, np.float64)
    K = np.asarray(K, np.float64)
    X = np.asarray(points, np.float64).reshape(-1, 3)
    Xc = np.einsum("...ij,...j->...i", T[..., :3, :3], X) + T[..., :3, 3]
    z = Xc[:, 2]
    zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
    uv = np.stack([K[..., 0, 0] * Xc[:, 0] / zs + K[..., 0, 2], K[..., 1, 1] * Xc[:, 1] / zs + K[..., 1, 2]], 1)
    return (uv, z) if with_depth else uv


def unproject(K: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Camera-frame rays (..., 3) with z = 1 through pixels (..., 2) of a pinhole camera with
    intrinsics ``K`` (broadcast against the pixels' leading dimensions): the inverse of :func:`project`."""
    K = np.asarray(K, np.float64)
    px = np.asarray(pixels, np.float64)
    xy = (px - K[..., :2, 2]) / np.stack([K[..., 0, 0], K[..., 1, 1]], -1)
    return np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], -1)


def sum_by_group(values: np.ndarray, group: np.ndarray, n: int) -> np.ndarray:
    """Per-group sums (n, ...) of per-item ``values`` (N, ...), in float64 (one ``np.bincount`` per
    entry: the sums ``np.add.at`` gives, in the same order, without its per-element cost: 1.9 s for
    the fox build's (20,634, 128) patch means against 0.02 s)."""
    flat = np.asarray(values).reshape(len(values), -1)
    out = np.zeros((n, flat.shape[1]))
    for k in range(flat.shape[1]):
        out[:, k] = np.bincount(group, flat[:, k], n)
    return out.reshape((n,) + np.shape(values)[1:])


def direction_cones(
    directions: np.ndarray, group: np.ndarray, n_groups: int, valid: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Per group of unit directions: the mean direction (unit, (G,3)) and the largest angle in degrees
    of one of its directions from that mean ((G,)). ``valid`` masks directions out of both."""
    d = np.asarray(directions, np.float64)
    ok = np.ones(len(d), bool) if valid is None else np.asarray(valid, bool)
    mean = sum_by_group(np.where(ok[:, None], d, 0.0), group, n_groups)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
    ang = np.degrees(np.arccos(np.clip(np.sum(d * mean[group], 1), -1, 1)))
    out = np.zeros(n_groups)
    np.maximum.at(out, group, np.where(ok, ang, 0.0))
    return mean, out


def view_geometry(points: np.ndarray, point_of_obs: np.ndarray, centers_of_obs: np.ndarray):
    """Per point of ``points`` (P, 3), from the camera centres (O, 3) of its observations
    (``point_of_obs`` (O,)): the mean viewing direction (unit, point -> cameras, (P, 3)), the largest
    angle in degrees of one of its views from it (P,), and the (min, max) distance of its views (P, 2)."""
    n = len(points)
    v = np.asarray(centers_of_obs, np.float64) - np.asarray(points, np.float64)[point_of_obs]
    dist = np.linalg.norm(v, axis=1)
    mean, amax = direction_cones(v / np.maximum(dist[:, None], 1e-12), point_of_obs, n)
    dmin = np.full(n, np.inf)
    dmax = np.zeros(n)
    np.minimum.at(dmin, point_of_obs, dist)
    np.maximum.at(dmax, point_of_obs, dist)
    return mean, amax, np.stack([dmin, dmax], 1)


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """The angle (degrees) of rotation matrices ``R`` (..., 3, 3)."""
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def pose_error(cam_from_world_est: np.ndarray, cam_from_world_gt: np.ndarray) -> tuple[float, float]:
    """(translation error in map units between camera centres, rotation error in degrees)."""
    dt = float(np.linalg.norm(camera_centers(cam_from_world_est) - camera_centers(cam_from_world_gt)))
    dR = cam_from_world_est[:3, :3] @ cam_from_world_gt[:3, :3].T
    return dt, float(rotation_angle_deg(dR))


def perturb_pose(cam_from_world: np.ndarray, trans: float, rot_deg: float, rng: np.random.Generator) -> np.ndarray:
    """Move a camera by exactly ``trans`` units (random direction) and rotate it by exactly
    ``rot_deg`` degrees (random axis) about its own centre."""
    wfc = inverse(cam_from_world)
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    a = rng.normal(size=3)
    wfc_new = wfc.copy()
    wfc_new[:3, :3] = rotation_about(a, np.radians(rot_deg)) @ wfc[:3, :3]
    wfc_new[:3, 3] = wfc[:3, 3] + trans * d
    return inverse(wfc_new)


def to_rigid3d(cam_from_world: np.ndarray):
    """4x4 -> pycolmap.Rigid3d."""
    import pycolmap

    return pycolmap.Rigid3d(pycolmap.Rotation3d(cam_from_world[:3, :3]), cam_from_world[:3, 3])


def from_rigid3d(rigid) -> np.ndarray:
    T = np.eye(4)
    T[:3, :4] = rigid.matrix()
    return T
