"""Aligning two maps of one place: their landmarks first, then the rays they were seen along.

``align_maps(a, b)`` estimates the similarity ``b_to_a`` (x_a = s R x_b + t) between two maps whose
poses live in different frames:

1. descriptor matches between landmarks: mutual nearest neighbours of the unit mean descriptors
   (``landmarks/mean_descriptor``) with a ratio test on the distances;
2. 3D-3D RANSAC with scale: a similarity (Umeyama) from 3 matches per hypothesis, hypotheses
   evaluated together in numpy; inliers are matches whose moved b-landmark lies within the
   threshold of its a-landmark (in a's units; default: twice the median voxel size of a's landmarks);
   Umeyama on the inliers until they stop changing;
3. refinement over both maps' observations (:mod:`favormap.ops.align_refine`): matches found again
   near each moved landmark (within 3, then 1 times the threshold), the similarity and the matched
   points fitted to the keypoints of every frame of either map that saw them, and the uncertainty from
   a jackknife over blocks of frames.

It refuses (:class:`AlignmentError`) when the maps do not overlap enough: too few matches, too few
inliers, an inlier ratio below the threshold or inliers that do not fix a similarity (collinear), so
a wrong transform is never reported as good.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FavormapError, IncompatibleMapsError
from ..geometry import rotation_angle_deg, transform_points, umeyama
from ..mapfile import Map
from .align_config import AlignConfig
from .align_refine import MapObservations, guided_matches, refine_alignment

# the refined matches reproject in both maps' frames more than this many times worse than each map's
# landmarks in its own frames: the two maps' poses disagree (a warning says so)
POSE_DISAGREEMENT_FACTOR = 2.0


class AlignmentError(FavormapError):
    """Two maps whose overlap does not determine a transform between them."""


@dataclass
class MapAlignment:
    """The estimated ``b_to_a`` (4x4 similarity: x_a = b_to_a @ x_b) and how well the maps agree."""

    b_to_a: np.ndarray
    scale: float
    num_landmarks: tuple  # (a, b)
    num_matches: int  # descriptor matches between the landmarks (stage 1)
    num_inliers: int  # of them, agreeing on one similarity (stage 2)
    inlier_ratio: float
    rms: float  # residual RMS of the inliers' landmark positions under b_to_a, in a's units
    threshold: float  # inlier distance used, in a's units
    num_refined_matches: int  # guided matches the refinement kept (stage 3)
    num_observations: int  # their observations in both maps' frames: the refinement's residuals
    reprojection_rms_px: float  # RMS reprojection error of those observations, working-image pixels
    std_translation_xyz: np.ndarray  # (3,) jackknife std of the translation per axis, a's units
    std_rotation_deg: float  # jackknife RMS rotation difference, degrees
    std_log_scale: float  # jackknife std of log(s)
    extent: float  # diagonal of the inliers' bounding box in a, a's units
    warnings: list = field(default_factory=list)

    @property
    def rotation_deg(self) -> float:
        return float(rotation_angle_deg(self.b_to_a[:3, :3] / self.scale))

    @property
    def std_translation(self) -> float:
        """Norm of the per-axis translation stds, a's units."""
        return float(np.linalg.norm(self.std_translation_xyz))

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
            "num_refined_matches": self.num_refined_matches,
            "num_observations": self.num_observations,
            "reprojection_rms_px": self.reprojection_rms_px,
            "std_translation": self.std_translation,
            "std_translation_xyz": self.std_translation_xyz.tolist(),
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


# -------------------------------------------------------------------------------------------------
# align
# -------------------------------------------------------------------------------------------------
def align_maps(path_a, path_b, config: AlignConfig | None = None) -> MapAlignment:
    """The similarity ``b_to_a`` between the maps at ``path_a`` and ``path_b`` (module docstring).
    Raises :class:`AlignmentError` when the maps do not overlap enough."""
    cfg = config or AlignConfig()
    with Map.open(path_a) as ma, Map.open(path_b) as mb:
        for k in ("extractor", "channels"):
            if getattr(ma, k) != getattr(mb, k):
                raise IncompatibleMapsError(
                    f"cannot align {ma.path} and {mb.path}: different {k} ({getattr(ma, k)!r} vs {getattr(mb, k)!r})"
                )
        a, b = MapObservations.read(ma), MapObservations.read(mb)
        voxel_size_a = np.asarray(ma.voxel_size, np.float64)
        names = (Path(ma.path).name, Path(mb.path).name)
    return align_observations(a, b, voxel_size_a, cfg, names)


def align_observations(
    a: MapObservations, b: MapObservations, voxel_size_a, cfg: AlignConfig, names=("a", "b")
) -> MapAlignment:
    """:func:`align_maps` on what it reads of the two maps."""
    T, matches, inl, threshold = landmark_similarity(
        a.positions, a.descriptors, b.positions, b.descriptors, voxel_size_a, cfg, names
    )
    for k, factor in enumerate(cfg.guided_radius):
        guided = guided_matches(a, b, T, factor * threshold, cfg.ratio)
        if len(guided) < cfg.min_inliers:
            raise AlignmentError(
                f"{names[0]} and {names[1]} do not overlap enough: {len(guided)} landmark matches near the "
                f"estimated transform (at least {cfg.min_inliers} needed)"
            )
        last = k == len(cfg.guided_radius) - 1
        refined = refine_alignment(a, b, guided, T, blocks=cfg.jackknife_blocks, uncertainty=last)
        T = refined.b_to_a
    pa, pb = a.positions[matches[inl, 0]], b.positions[matches[inl, 1]]
    res = np.linalg.norm(transform_points(T, pb) - pa, axis=1)
    scale = float(np.cbrt(np.linalg.det(T[:3, :3])))
    own = np.concatenate([a.reproj_error[refined.matches[:, 0]], b.reproj_error[refined.matches[:, 1]]])
    own_rms = float(np.sqrt(np.mean(own**2)))
    warnings = []
    if refined.reprojection_rms_px > POSE_DISAGREEMENT_FACTOR * own_rms:
        warnings.append(
            f"the maps' poses disagree beyond each map's own fit: the matched points reproject with RMS "
            f"{refined.reprojection_rms_px:.2f} px in both maps' frames against {own_rms:.2f} px in each "
            "map's own; the stated stds cover the matches' noise, not this disagreement"
        )
    return MapAlignment(
        b_to_a=T,
        scale=scale,
        num_landmarks=(len(a.positions), len(b.positions)),
        num_matches=len(matches),
        num_inliers=int(inl.sum()),
        inlier_ratio=float(inl.sum() / len(matches)),
        rms=float(np.sqrt(np.mean(res**2))),
        threshold=float(threshold),
        num_refined_matches=len(refined.matches),
        num_observations=refined.num_observations,
        reprojection_rms_px=refined.reprojection_rms_px,
        std_translation_xyz=refined.std_translation_xyz,
        std_rotation_deg=refined.std_rotation_deg,
        std_log_scale=refined.std_log_scale,
        extent=float(np.linalg.norm(pa.max(0) - pa.min(0))),
        warnings=warnings,
    )


def landmark_similarity(pa_all, da, pb_all, db, voxel_size_a, cfg: AlignConfig, names=("a", "b")) -> tuple:
    """Stages 1 and 2 (module docstring) on the landmarks' positions and mean descriptors: (b_to_a,
    matches (K, 2), inlier mask (K,), inlier threshold). Raises :class:`AlignmentError` when they do
    not fix a similarity."""
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
    T, inl = ransac_similarity(pa, pb, threshold, cfg.iterations, np.random.default_rng(cfg.seed))
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
    return T, matches, inl, threshold


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
