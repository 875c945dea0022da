"""triangulation: DLT initialisation + robust Levenberg-Marquardt, batched over all tracks.

The refinement follows the paper's supplement: the landmark is parameterised by inverse depth
(alpha, beta, rho) in an anchor camera of its track, the residual is the reprojection error and the
cost is Geman-McClure (solved by iteratively re-weighted, damped Gauss-Newton steps). Tracks are
not padded: every step is one numpy operation over all observations, sums per track by bincount.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import apply_homographies, camera_centers, direction_cones, inverse, plane_homographies, sum_by_group
from .io.images import sample_bilinear
from .tracking import Tracks


@dataclass
class TriangulationConfig:
    max_reproj_px: float = 5.0
    min_angle_deg: float = 1.0
    robust_c_px: float = 3.0
    iterations: int = 15
    min_track: int = 5


@dataclass
class Landmarks:
    """Triangulated tracks: stage boundary between triangulation and voxels."""

    positions: np.ndarray  # (L, 3) world
    tracks: Tracks  # observations, track j <-> landmark j
    reproj_errors: np.ndarray  # (O,) pixels, per observation
    angles_deg: np.ndarray  # (L,) maximal triangulation angle
    source: np.ndarray | None = None  # (L,) index of each landmark's track in triangulate()'s input

    def __len__(self) -> int:
        return len(self.positions)

    @property
    def mean_reproj_error(self) -> np.ndarray:
        tid = self.tracks.track_of_obs
        return np.bincount(tid, self.reproj_errors, len(self)) / np.maximum(self.tracks.lengths, 1)

    def select(self, idx: np.ndarray) -> Landmarks:
        idx = np.asarray(idx)
        keep_obs = np.isin(self.tracks.track_of_obs, idx)
        tr = self.tracks.select(keep_obs)
        idx = np.sort(idx)  # Tracks.select keeps the track order
        src = None if self.source is None else self.source[idx]
        return Landmarks(self.positions[idx], tr, self.reproj_errors[keep_obs], self.angles_deg[idx], src)


def dlt(P: np.ndarray, xy: np.ndarray, tid: np.ndarray, n: int) -> np.ndarray:
    """Batched linear triangulation of ``n`` tracks. P: (O, 3, 4) projection matrices (pixels) of the
    observations, xy: (O, 2) their pixels, tid: (O,) their track.

    Each observation gives two rows of the track's DLT system A X = 0 (normalised for conditioning);
    the solution is the eigenvector of the smallest eigenvalue of A^T A, accumulated per track as a
    4 x 4 sum, so memory grows with the observations, not with tracks x the longest track."""
    r1 = xy[:, 0:1] * P[:, 2, :] - P[:, 0, :]
    r2 = xy[:, 1:2] * P[:, 2, :] - P[:, 1, :]
    r1 = r1 / np.maximum(np.linalg.norm(r1, axis=1, keepdims=True), 1e-12)
    r2 = r2 / np.maximum(np.linalg.norm(r2, axis=1, keepdims=True), 1e-12)
    M = sum_by_group(r1[:, :, None] * r1[:, None, :] + r2[:, :, None] * r2[:, None, :], tid, n)
    _, vecs = np.linalg.eigh(M)
    X = vecs[:, :, 0]
    return X[:, :3] / np.where(np.abs(X[:, 3:]) < 1e-12, 1e-12, X[:, 3:])


BLOCK_OBSERVATIONS = 200_000  # observations triangulated at once (memory ~1 KB each while working)


def triangulate(
    tracks: Tracks, cam_from_world: np.ndarray, Ks: np.ndarray, config: TriangulationConfig | None = None
) -> Landmarks:
    """Triangulate every track. ``cam_from_world``: (M,4,4) per frame; ``Ks``: (M,3,3) pinhole.

    Tracks are independent: they are solved in blocks of about ``BLOCK_OBSERVATIONS`` observations,
    so the working memory does not grow with the sequence."""
    config = TriangulationConfig() if config is None else config
    if len(tracks) == 0:
        return Landmarks(np.zeros((0, 3)), tracks, np.zeros(0), np.zeros(0), np.zeros(0, np.int64))
    cuts = np.searchsorted(tracks.offsets, np.arange(0, tracks.offsets[-1], BLOCK_OBSERVATIONS), side="right") - 1
    bounds = np.unique(np.concatenate([cuts, [len(tracks)]]))
    if len(bounds) <= 2:
        return _triangulate_block(tracks, cam_from_world, Ks, config)
    parts = [
        _triangulate_block(tracks.range(lo, hi), cam_from_world, Ks, config) for lo, hi in zip(bounds[:-1], bounds[1:])
    ]
    return Landmarks(
        np.concatenate([p.positions for p in parts]),
        Tracks.concat([p.tracks for p in parts]),
        np.concatenate([p.reproj_errors for p in parts]),
        np.concatenate([p.angles_deg for p in parts]),
        np.concatenate([p.source + lo for p, lo in zip(parts, bounds[:-1])]),
    )


def _triangulate_block(
    tracks: Tracks, cam_from_world: np.ndarray, Ks: np.ndarray, config: TriangulationConfig
) -> Landmarks:
    """The tracks triangulated linearly (:func:`dlt`), refined robustly in inverse depth and checked."""
    fi = tracks.frame_idx
    X0 = dlt(Ks[fi] @ cam_from_world[fi, :3, :], tracks.xy, tracks.track_of_obs, len(tracks))
    problem = _AnchoredTracks.of(tracks, cam_from_world, Ks[fi], config.robust_c_px)
    theta, e = _refine_inverse_depths(problem, problem.theta_of(X0), config.iterations)
    return _checked_landmarks(tracks, cam_from_world, problem.points(theta), theta[:, 2], e, config)


@dataclass
class _AnchoredTracks:
    """Each track's landmark in inverse depth theta = (alpha, beta, rho) in the camera of the track's first
    frame (its anchor): in an observation's camera the landmark is h = A m + rho b, m = (alpha, beta, 1).
    Per-observation arrays are kept component by component (last axis: the observations), so that every
    step of the refinement runs on contiguous rows."""

    tid: np.ndarray  # (O,) track of each observation
    xy: np.ndarray  # (2, O) its pixel
    dh: np.ndarray  # (3, 3, O) dh/dtheta, [component of h, of theta]: the columns A[:, :, 0], A[:, :, 1], b
    a2: np.ndarray  # (3, O) A[:, :, 2]
    f: np.ndarray  # (2, O) its camera's focal lengths
    c: np.ndarray  # (2, O) and principal point
    R_wa: np.ndarray  # (T, 3, 3) world from anchor rotation
    c_a: np.ndarray  # (T, 3) anchor camera centre
    c2: float  # squared scale of the robust (Geman-McClure) cost, px^2

    @classmethod
    def of(cls, tracks: Tracks, cam_from_world: np.ndarray, K: np.ndarray, robust_c_px: float) -> _AnchoredTracks:
        fi, tid = tracks.frame_idx, tracks.track_of_obs
        Rcw = cam_from_world[fi, :3, :3]  # (O,3,3)
        tcw = cam_from_world[fi, :3, 3]
        anchor = tracks.frame_idx[tracks.offsets[:-1]]  # first frame of each track
        wfc_a = inverse(cam_from_world[anchor])
        R_wa, c_a = wfc_a[:, :3, :3], wfc_a[:, :3, 3]
        A = Rcw @ R_wa[tid]  # (O,3,3)
        b = np.einsum("oij,oj->oi", Rcw, c_a[tid]) + tcw  # (O,3)
        dh = np.ascontiguousarray(np.concatenate([A[:, :, :2], b[:, :, None]], 2).transpose(1, 2, 0))
        return cls(
            tid,
            np.ascontiguousarray(np.asarray(tracks.xy, np.float64).T),
            dh,
            np.ascontiguousarray(A[:, :, 2].T),
            np.stack([K[:, 0, 0], K[:, 1, 1]]),
            np.stack([K[:, 0, 2], K[:, 1, 2]]),
            R_wa,
            c_a,
            robust_c_px**2,
        )

    @property
    def n(self) -> int:
        return len(self.R_wa)

    def theta_of(self, X: np.ndarray) -> np.ndarray:
        """(T, 3) inverse-depth parameters of world points ``X`` (T, 3)."""
        Xa = np.einsum("tji,tj->ti", self.R_wa, X - self.c_a)  # landmark in anchor camera
        za = np.where(np.abs(Xa[:, 2]) < 1e-6, 1e-6, Xa[:, 2])
        return np.stack([Xa[:, 0] / za, Xa[:, 1] / za, 1.0 / za], 1)  # (T,3): alpha, beta, rho

    def points(self, theta: np.ndarray) -> np.ndarray:
        """(T, 3) world points of ``theta``."""
        rho = theta[:, 2]
        rho_safe = np.where(np.abs(rho) < 1e-12, 1e-12, rho)
        Xa = np.stack([theta[:, 0], theta[:, 1], np.ones(len(theta))], 1) / rho_safe[:, None]
        return np.einsum("tij,tj->ti", self.R_wa, Xa) + self.c_a

    def residuals(self, th: np.ndarray):
        """(2, O) pixel residuals, and h (3, O) with its guarded depth hz (O,)."""
        t = th.T[:, self.tid]  # (3, O)
        dh = self.dh
        h = dh[:, 0] * t[0] + dh[:, 1] * t[1] + self.a2 + t[2] * dh[:, 2]
        hz = np.where(np.abs(h[2]) < 1e-9, 1e-9, h[2])
        return self.f * h[:2] / hz + self.c - self.xy, h, hz

    def cost(self, e: np.ndarray) -> np.ndarray:
        """(T,) robust cost of each track."""
        c2 = self.c2
        u2 = e[0] * e[0] + e[1] * e[1]
        return np.bincount(self.tid, 0.5 * c2 * u2 / (c2 + u2), self.n)

    def jacobian(self, h: np.ndarray, hz: np.ndarray) -> np.ndarray:
        """(2, 3, O) Jacobian of the pixels (u, v) with respect to theta."""
        dh = self.dh
        dz = dh[2] / hz**2
        return self.f[:, None] * (dh[:2] / hz - h[:2, None] * dz)


# the six entries (i <= j) of a symmetric 3 x 3 normal matrix
_UPPER = np.triu_indices(3)


def _refine_inverse_depths(problem: _AnchoredTracks, theta: np.ndarray, iterations: int):
    """Levenberg-Marquardt on the robust cost, every track at once (Geman-McClure IRLS weights, a damping
    per track); returns theta and the final pixel residuals (O, 2)."""
    tid, n, c2 = problem.tid, problem.n, problem.c2
    lam = np.full(n, 1e-3)
    e, h, hz = problem.residuals(theta)
    cur = problem.cost(e)
    i, j = _UPPER
    for _ in range(iterations):
        w = (c2 / (c2 + (e[0] * e[0] + e[1] * e[1]))) ** 2  # Geman-McClure IRLS weight
        J = problem.jacobian(h, hz)
        H = np.empty((n, 3, 3))
        # per-track sums of the (k, O) rows: sum_by_group reads each row of the transposed view contiguously
        H[:, i, j] = H[:, j, i] = sum_by_group((w * (J[0, i] * J[0, j] + J[1, i] * J[1, j])).T, tid, n)
        g = sum_by_group((w * (J[0] * e[0] + J[1] * e[1])).T, tid, n)
        Hd = H + lam[:, None, None] * (np.eye(3) * np.maximum(np.diagonal(H, axis1=1, axis2=2), 1e-9)[:, None, :])
        try:
            step = -np.linalg.solve(Hd, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            step = -np.einsum("tij,tj->ti", np.linalg.pinv(Hd), g)
        cand = theta + step
        e_c, h_c, hz_c = problem.residuals(cand)
        new = problem.cost(e_c)
        better = np.isfinite(new) & (new < cur)
        theta = np.where(better[:, None], cand, theta)
        lam = np.where(better, lam * 0.3, lam * 10.0).clip(1e-9, 1e9)
        cur = np.where(better, new, cur)
        took = better[tid]  # the residuals at the kept parameters: the candidate's where it was taken
        e, h, hz = np.where(took, e_c, e), np.where(took, h_c, h), np.where(took, hz_c, hz)
    return theta, e.T


def _checked_landmarks(
    tracks: Tracks,
    cam_from_world: np.ndarray,
    X: np.ndarray,
    rho: np.ndarray,
    e: np.ndarray,
    config: TriangulationConfig,
) -> Landmarks:
    """The landmarks ``X`` less the observations reprojected beyond ``max_reproj_px`` or behind their
    camera, then less the tracks seen under less than ``min_angle_deg``, at negative inverse depth
    ``rho`` or left shorter than ``min_track``."""
    fi, tid = tracks.frame_idx, tracks.track_of_obs
    Rcw, tcw = cam_from_world[fi, :3, :3], cam_from_world[fi, :3, 3]
    err = np.linalg.norm(e, axis=1)
    depth = np.einsum("oj,oj->o", Rcw[:, 2], X[tid]) + tcw[:, 2]
    ok_obs = (err <= config.max_reproj_px) & (depth > 0) & np.isfinite(err) & np.isfinite(X[tid]).all(1)
    centers = camera_centers(cam_from_world[fi])
    rays = X[tid] - centers
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
    angles = _max_angle(rays, tracks, ok_obs)
    track_ok = (angles >= config.min_angle_deg) & (rho > 0)
    keep = ok_obs & track_ok[tid]
    counts = np.bincount(tid[keep], minlength=len(tracks))
    keep &= counts[tid] >= config.min_track
    kept_tracks = np.flatnonzero(np.bincount(tid[keep], minlength=len(tracks)) > 0)
    new_tracks = tracks.select(keep)
    return Landmarks(X[kept_tracks], new_tracks, err[keep], angles[kept_tracks], kept_tracks)


def _max_angle(rays: np.ndarray, tracks: Tracks, valid: np.ndarray) -> np.ndarray:
    """Largest angle (degrees) between the valid viewing rays of each track (vs. their mean ray)."""
    _, out = direction_cones(rays, tracks.track_of_obs, len(tracks), valid)
    return 2.0 * out  # spread of the rays ~ twice the largest deviation from the mean


def landmark_normals(positions: np.ndarray, toward: np.ndarray, k: int = 12) -> np.ndarray:
    """Unit normals (L, 3) of the surface the landmarks lie on: the direction of least spread of each
    landmark's ``k`` nearest landmarks (PCA), turned toward ``toward`` (L, 3), e.g. a camera centre."""
    from scipy.spatial import cKDTree

    n = len(positions)
    if n == 0:
        return np.zeros((0, 3))
    _, nn = cKDTree(positions).query(positions, k=min(k, n))
    nn = nn.reshape(n, -1)
    Y = positions[nn] - positions[nn].mean(1, keepdims=True)
    normal = np.linalg.eigh(np.einsum("nki,nkj->nij", Y, Y))[1][:, :, 0]  # eigenvalues ascending
    return normal * np.where(np.einsum("ni,ni->n", normal, toward - positions) < 0, -1.0, 1.0)[:, None]


# observations refine_observations aligns at a time (~60 MB of samples at a 9 x 9 window)
REFINE_BLOCK = 32768


def refine_observations(
    lms: Landmarks,
    grays,
    K: np.ndarray,
    cam_from_world: np.ndarray,
    window: int = 9,
    normal_k: int = 12,
    iterations: int = 10,
    max_move_px: float = 1.5,
    normals: np.ndarray | None = None,
) -> tuple[Tracks, np.ndarray]:
    """Each landmark's observations aligned to its middle observation (in frame order) by their image
    content, through the homography of the landmark's local plane: the keypoints of a track are each
    detected on their own, with their own noise; this moves observation b to where the reference's
    ``window`` x ``window`` neighbourhood, carried into frame b by the plane through the landmark with
    the normal of its ``normal_k`` nearest landmarks (:func:`landmark_normals`), matches frame b best
    (Lucas-Kanade over a 2D shift in the reference frame, gain and offset removed, ``iterations``
    Gauss-Newton steps). An observation moves at most ``max_move_px``; otherwise it stays where it
    was detected, as does the reference. ``grays``: the frames' grey images at the keypoints'
    resolution; ``normals`` (L, 3): the planes' normals where they are known (a mesh), instead of the
    PCA. Returns the tracks (triangulate them again) and which observations moved.

    On the synthetic room with exact poses it brings the landmarks about 2.5x closer to the true
    surface (tests/test_build.py); a translation-only alignment without the plane moved them off it."""
    tracks = lms.tracks
    xy = tracks.xy.copy()
    moved = np.zeros(len(xy), bool)
    if len(lms) == 0:
        return tracks, moved
    warps = _PlaneWarps.of(lms, K, cam_from_world, normals, normal_k)
    frames = _GreyFrames(grays)
    half = window // 2
    g = (
        np.stack(np.meshgrid(np.arange(-half, half + 1), np.arange(-half, half + 1)), -1)
        .reshape(-1, 2)
        .astype(np.float64)
    )
    s = np.zeros((len(warps.todo), 2))
    for lo in range(0, len(warps.todo), REFINE_BLOCK):  # bounded memory: (block, window^2) samples at a time
        blk = np.arange(lo, min(lo + REFINE_BLOCK, len(warps.todo)))
        s[blk] = _align_block(warps, blk, g, frames, iterations)
    todo = warps.todo
    pb = apply_homographies(warps.H, (warps.pa + s)[:, None])[:, 0]
    ok = np.isfinite(pb).all(1) & (np.linalg.norm(pb - tracks.xy[todo], axis=1) <= max_move_px)
    xy[todo[ok]] = pb[ok]
    moved[todo[ok]] = True
    return Tracks(tracks.frame_idx, tracks.keypoint_idx, xy, tracks.offsets), moved


@dataclass
class _PlaneWarps:
    """Each observation to align (all but its track's reference, the middle one) with the homography that
    carries its reference's pixels into its frame through the landmark's plane."""

    todo: np.ndarray  # (N,) observations to align
    fa: np.ndarray  # (N,) frame of each one's reference
    fb: np.ndarray  # (N,) its own frame
    H: np.ndarray  # (N, 3, 3) reference pixels -> its frame
    pa: np.ndarray  # (N, 2) the reference keypoint

    @classmethod
    def of(cls, lms: Landmarks, K, cam_from_world, normals, normal_k: int) -> _PlaneWarps:
        tracks = lms.tracks
        lens = tracks.lengths
        ref = np.repeat(tracks.offsets[:-1] + lens // 2, lens)  # observations are sorted by frame within a track
        tid = tracks.track_of_obs
        centers = camera_centers(cam_from_world)
        if normals is None:
            middle = tracks.frame_idx[tracks.offsets[:-1] + lens // 2]
            normals = landmark_normals(lms.positions, centers[middle], normal_k)
        T = np.asarray(cam_from_world, np.float64)
        K = np.broadcast_to(np.asarray(K, np.float64), (len(T), 3, 3))
        todo = np.flatnonzero(np.arange(len(tracks.xy)) != ref)
        fa, fb = tracks.frame_idx[ref[todo]].astype(np.int64), tracks.frame_idx[todo].astype(np.int64)
        H = plane_homographies(K[fa], T[fa], K[fb], T[fb], lms.positions[tid[todo]], normals[tid[todo]])
        return cls(todo, fa, fb, H, tracks.xy[ref[todo]])


class _GreyFrames:
    """The frames' grey images as float32, each with its gradients (central differences), made on first use."""

    def __init__(self, grays):
        self.grays = grays
        self.held: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, f: int) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) image and (H, W, 3) image, d/dx, d/dy."""
        import cv2

        if f not in self.held:
            im = np.ascontiguousarray(self.grays[f], np.float32)
            sobel = [cv2.Sobel(im, cv2.CV_32F, dx, 1 - dx, ksize=1) * 0.5 for dx in (1, 0)]
            self.held[f] = im, np.stack([im] + sobel, -1)
        return self.held[f]


def _align_block(warps: _PlaneWarps, blk: np.ndarray, g: np.ndarray, frames: _GreyFrames, iterations: int):
    """(n, 2) shifts in the reference frames that align observations ``blk`` to their references:
    Lucas-Kanade with gain and offset removed, ``iterations`` Gauss-Newton steps over window offsets ``g``."""
    fa, fb = warps.fa[blk], warps.fb[blk]
    grid = warps.pa[blk, None] + g[None]
    # the reference templates and their gradients, frame by frame of the references (one lookup each)
    A, J = np.zeros(grid.shape[:2]), np.zeros(grid.shape[:2] + (2,))
    for a in np.unique(fa):
        rows = np.flatnonzero(fa == a)
        v = sample_bilinear(frames(a)[1], grid[rows])
        A[rows], J[rows] = v[..., 0], v[..., 1:]
    A -= A.mean(1, keepdims=True)
    J -= J.mean(1, keepdims=True)
    Jt = J.transpose(0, 2, 1)
    step = np.linalg.inv(Jt @ J + 1e-6 * np.eye(2)) @ Jt  # (n, 2, G): Gauss-Newton's step from the residuals
    # Lucas-Kanade, all observations in one frame a step at a time (one lookup of that frame)
    by_frame = [(b, np.flatnonzero(fb == b)) for b in np.unique(fb)]
    sb, Hb = np.zeros((len(blk), 2)), warps.H[blk]
    for _ in range(iterations):
        for b, rows in by_frame:
            W = sample_bilinear(frames(b)[0], apply_homographies(Hb[rows], grid[rows] + sb[rows, None]))
            e = W - W.mean(1, keepdims=True) - A[rows]
            sb[rows] -= (step[rows] @ e[..., None])[..., 0]
    return sb
