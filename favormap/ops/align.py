"""Aligning two maps of one place from their landmarks alone.

``align_maps(a, b)`` estimates the similarity ``b_to_a`` (x_a = s R x_b + t) between two maps whose
poses live in different frames:

1. descriptor matches between landmarks: mutual nearest neighbours of the unit mean descriptors
   (``landmarks/mean_descriptor``) with a ratio test on the distances;
2. 3D-3D RANSAC with scale: a similarity (Umeyama) from 3 matches per hypothesis, hypotheses
   evaluated together in numpy; inliers are matches whose moved b-landmark lies within the
   threshold of its a-landmark (in a's units; default: twice the median voxel size of a's landmarks);
3. refinement: Umeyama on all inliers, inliers recomputed, until they stop changing;
4. uncertainty: a bootstrap over the inliers (std of the translation, of the rotation in degrees and
   of log-scale).

It refuses (:class:`AlignmentError`) when the maps do not overlap enough: too few matches, too few
inliers, an inlier ratio below the threshold or inliers that do not fix a similarity (collinear), so
a wrong transform is never reported as good.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FavormapError, IncompatibleMapsError
from ..geometry import umeyama
from ..mapfile import Map
from .align_config import AlignConfig


class AlignmentError(FavormapError):
    """Two maps whose overlap does not determine a transform between them."""


@dataclass
class MapAlignment:
    """The estimated ``b_to_a`` (4x4 similarity: x_a = b_to_a @ x_b) and how well the maps agree."""

    b_to_a: np.ndarray
    scale: float
    num_landmarks: tuple  # (a, b)
    num_matches: int
    num_inliers: int
    inlier_ratio: float
    rms: float  # residual RMS of the inliers, in a's units
    threshold: float  # inlier distance used, in a's units
    std_translation: float  # bootstrap std of t (norm of the per-axis stds), a's units
    std_rotation_deg: float  # bootstrap RMS rotation difference, degrees
    std_log_scale: float  # bootstrap std of log(s)
    extent: float  # diagonal of the inliers' bounding box in a, a's units
    warnings: list = field(default_factory=list)

    @property
    def rotation_deg(self) -> float:
        R = self.b_to_a[:3, :3] / self.scale
        return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))

    def to_dict(self) -> dict:
        return {
            "b_to_a": self.b_to_a.tolist(),
            "scale": self.scale,
            "rotation_deg": self.rotation_deg,
            "translation": self.b_to_a[:3, 3].tolist(),
            "num_landmarks": list(self.num_landmarks),
            "num_matches": self.num_matches,
            "num_inliers": self.num_inliers,
            "inlier_ratio": self.inlier_ratio,
            "rms": self.rms,
            "threshold": self.threshold,
            "std_translation": self.std_translation,
            "std_rotation_deg": self.std_rotation_deg,
            "std_log_scale": self.std_log_scale,
            "inlier_extent": self.extent,
            "warnings": self.warnings,
        }


# -------------------------------------------------------------------------------------------------
# pieces
# -------------------------------------------------------------------------------------------------
def mutual_matches(da: np.ndarray, db: np.ndarray, ratio: float, chunk: int = 2048) -> np.ndarray:
    """(K, 2) rows (i in a, j in b) of mutual nearest neighbours of unit descriptors whose
    nearest / second-nearest distance ratio is below ``ratio`` both ways."""
    da = _unit(da)
    db = _unit(db)
    if len(da) < 2 or len(db) < 2:
        return np.zeros((0, 2), np.int64)

    def best_two(x, y):
        nn = np.zeros(len(x), np.int64)
        s1 = np.zeros(len(x))
        s2 = np.zeros(len(x))
        for a in range(0, len(x), chunk):
            S = x[a : a + chunk] @ y.T
            top = np.argpartition(-S, 1, axis=1)[:, :2]
            st = np.take_along_axis(S, top, 1)
            o = np.argsort(-st, 1)
            top, st = np.take_along_axis(top, o, 1), np.take_along_axis(st, o, 1)
            nn[a : a + chunk], s1[a : a + chunk], s2[a : a + chunk] = top[:, 0], st[:, 0], st[:, 1]
        # distances of unit vectors: d^2 = 2 - 2 cos
        d1 = np.sqrt(np.maximum(2 - 2 * s1, 0))
        d2 = np.sqrt(np.maximum(2 - 2 * s2, 0))
        return nn, d1 < ratio * d2

    ab, ok_a = best_two(da, db)
    ba, ok_b = best_two(db, da)
    i = np.arange(len(da))
    keep = ok_a & (ba[ab] == i) & ok_b[ab]
    return np.stack([i[keep], ab[keep]], 1)


def _residuals(T: np.ndarray, pb: np.ndarray, pa: np.ndarray) -> np.ndarray:
    return np.linalg.norm(pb @ T[:3, :3].T + T[:3, 3] - pa, axis=1)


def ransac_similarity(pa: np.ndarray, pb: np.ndarray, threshold: float, iterations: int, rng) -> tuple:
    """(T, inlier mask) of the similarity with most inliers among ``iterations`` 3-point hypotheses,
    refined on its inliers until they stop changing (T None when no hypothesis is valid)."""
    K = len(pa)
    if K < 3:
        return None, np.zeros(K, bool)
    best_T, best_n = None, -1
    batch = 500
    for a in range(0, iterations, batch):
        m = min(batch, iterations - a)
        idx = np.stack([rng.choice(K, 3, replace=False) for _ in range(m)]) if K < 6 else rng.integers(0, K, (m, 3))
        sa, sb = pa[idx], pb[idx]
        area_a = np.linalg.norm(np.cross(sa[:, 1] - sa[:, 0], sa[:, 2] - sa[:, 0]), axis=1)
        area_b = np.linalg.norm(np.cross(sb[:, 1] - sb[:, 0], sb[:, 2] - sb[:, 0]), axis=1)
        ok = (area_a > threshold**2) & (area_b > 1e-12) & (idx[:, 0] != idx[:, 1])
        ok &= (idx[:, 0] != idx[:, 2]) & (idx[:, 1] != idx[:, 2])
        if not ok.any():
            continue
        T = umeyama(sb[ok], sa[ok])  # (h, 4, 4): a from b
        moved = np.einsum("hij,kj->hki", T[:, :3, :3], pb) + T[:, None, :3, 3]
        n_in = np.sum(np.linalg.norm(moved - pa[None], axis=2) < threshold, 1)
        h = int(np.argmax(n_in))
        if n_in[h] > best_n:
            best_n, best_T = int(n_in[h]), T[h]
    if best_T is None:
        return None, np.zeros(K, bool)
    inl = _residuals(best_T, pb, pa) < threshold
    for _ in range(10):
        if inl.sum() < 3:
            break
        T = umeyama(pb[inl], pa[inl])
        new = _residuals(T, pb, pa) < threshold
        if new.sum() < inl.sum():
            break
        best_T = T
        if np.array_equal(new, inl):
            break
        inl = new
    return best_T, _residuals(best_T, pb, pa) < threshold


def _rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    tr = np.trace(R, axis1=-2, axis2=-1)
    return np.degrees(np.arccos(np.clip((tr - 1) / 2, -1, 1)))


def _scale_rotation(T: np.ndarray):
    s = np.cbrt(np.linalg.det(T[..., :3, :3]))
    return s, T[..., :3, :3] / s[..., None, None]


# -------------------------------------------------------------------------------------------------
# align
# -------------------------------------------------------------------------------------------------
def align_maps(path_a, path_b, config: AlignConfig | None = None) -> MapAlignment:
    """The similarity ``b_to_a`` between the maps at ``path_a`` and ``path_b`` from their landmarks.
    Raises :class:`AlignmentError` when the maps do not overlap enough (see the module docstring)."""
    cfg = config or AlignConfig()
    with Map.open(path_a) as ma, Map.open(path_b) as mb:
        for k in ("extractor", "channels"):
            if getattr(ma, k) != getattr(mb, k):
                raise IncompatibleMapsError(
                    f"cannot align {ma.path} and {mb.path}: different {k} ({getattr(ma, k)!r} vs {getattr(mb, k)!r})"
                )
        pa_all = np.asarray(ma.positions, np.float64)
        pb_all = np.asarray(mb.positions, np.float64)
        vs_a = np.asarray(ma.voxel_size, np.float64)
        da = ma.mean_descriptors(np.arange(len(ma)))
        db = mb.mean_descriptors(np.arange(len(mb)))
        names = (Path(ma.path).name, Path(mb.path).name)
    return align_landmarks(pa_all, da, pb_all, db, vs_a, cfg, names)


def align_landmarks(pa_all, da, pb_all, db, voxel_size_a, cfg: AlignConfig, names=("a", "b")) -> MapAlignment:
    """:func:`align_maps` on arrays: positions and mean descriptors of both maps' landmarks."""
    a_name, b_name = names
    threshold = cfg.threshold
    if threshold is None:
        threshold = 2.0 * float(np.median(voxel_size_a)) if len(voxel_size_a) else 0.0
    if not (threshold > 0 and np.isfinite(threshold)):
        raise AlignmentError(f"the inlier threshold must be a finite number > 0, got {threshold}")
    matches = mutual_matches(da, db, cfg.ratio)
    K = len(matches)
    if K < cfg.min_matches:
        raise AlignmentError(
            f"{a_name} and {b_name} do not overlap enough: {K} descriptor matches between landmarks "
            f"(at least {cfg.min_matches} needed)"
        )
    pa, pb = pa_all[matches[:, 0]], pb_all[matches[:, 1]]
    rng = np.random.default_rng(cfg.seed)
    T, inl = ransac_similarity(pa, pb, threshold, cfg.iterations, rng)
    n_in = int(inl.sum())
    ratio = n_in / K
    if T is None or n_in < cfg.min_inliers or ratio < cfg.min_inlier_ratio:
        raise AlignmentError(
            f"{a_name} and {b_name} do not overlap enough: {n_in} of {K} landmark matches agree on one "
            f"transform ({100 * ratio:.0f} %; at least {cfg.min_inliers} and {100 * cfg.min_inlier_ratio:.0f} % needed)"
        )
    qa = pa[inl]
    sv = np.linalg.svd(qa - qa.mean(0), compute_uv=False)
    if sv[1] < cfg.min_spread * sv[0]:
        raise AlignmentError(
            f"{a_name} and {b_name}: the {n_in} agreeing landmarks are nearly collinear, they do not fix a "
            "transform (degenerate overlap)"
        )
    res = _residuals(T, pb[inl], qa)
    rms = float(np.sqrt(np.mean(res**2)))
    s, R = _scale_rotation(T)
    # bootstrap over the inliers
    ib = np.flatnonzero(inl)
    boot = rng.integers(0, n_in, (cfg.bootstrap, n_in))
    Tb = umeyama(pb[ib][boot], pa[ib][boot])
    sb, Rb = _scale_rotation(Tb)
    std_t = float(np.linalg.norm(np.std(Tb[:, :3, 3], axis=0)))
    std_r = float(np.sqrt(np.mean(_rotation_angle_deg(Rb @ R.T) ** 2)))
    std_ls = float(np.std(np.log(sb)))
    extent = float(np.linalg.norm(qa.max(0) - qa.min(0)))
    return MapAlignment(
        b_to_a=T,
        scale=float(s),
        num_landmarks=(len(pa_all), len(pb_all)),
        num_matches=K,
        num_inliers=n_in,
        inlier_ratio=float(ratio),
        rms=rms,
        threshold=float(threshold),
        std_translation=std_t,
        std_rotation_deg=std_r,
        std_log_scale=std_ls,
        extent=extent,
    )


def write_transform(path, T: np.ndarray) -> None:
    """``T`` as the 4x4 text file ``merge --transform`` reads, written atomically."""
    import os
    import tempfile

    from ..errors import InputError

    path = Path(path)
    if not path.parent.is_dir():
        raise InputError(f"cannot write {path}: folder {path.parent} does not exist")
    if path.is_dir():
        raise InputError(f"cannot write {path}: it is a folder")
    fd, tmp = tempfile.mkstemp(dir=path.parent if str(path.parent) else ".", prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            np.savetxt(f, np.asarray(T, np.float64), fmt="%.17g")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _unit(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float32)
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)
