"""Query keypoints aligned to the mapping images through each landmark's local plane.

A SIFT keypoint's position moves with the view: where a blob is detected on a slanted textured
surface shifts by a fraction of a pixel as the camera moves round it, and the inliers of one query,
seen from one side, shift alike, which moves the pose (twenty-eighth / twenty-ninth sessions,
docs/accuracy.md). This stage replaces each inlier's detected keypoint, before the final weighted
refinement, by where the landmark's appearance in a mapping image lies in the query: the query's
``(2h+1)^2`` pixels around the landmark's predicted projection are carried through the plane through
the landmark (normal from its nearest landmarks, :func:`favormap.triangulation.landmark_normals`)
into the mapping frame that saw the landmark from the nearest direction, and a Lucas-Kanade
alignment (2D shift, gain and offset; PTAM / SVO-style feature alignment) finds the shift in the
query that matches that template best. The alignment is kept where it converged (normalised
cross-correlation >= ``min_ncc``) within ``max_shift_px`` of the detected keypoint.

It needs the mapping images (the map does not store them): the folder the map was built from (its
provenance), or another folder of the same sequence. Measured with tools/bench_accuracy.py (see
docs/accuracy.md, twenty-ninth session): on the synthetic orbit with exact poses 0.54x the error of
the detected keypoints, 0.20x on a map whose tracks were aligned the same way
(``BuildConfig.refine_window``), 0.35x the pycolmap baseline's; on the real fox sequence, whose poses
come from COLMAP, 1.1-1.3x worse: an option, off by default.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry import camera_centers, plane_points, project
from ..io.images import sample_bilinear, working_camera
from .observations import ObservationIndex


@dataclass(frozen=True)
class AlignConfig:
    half: int = 5  # template of (2 half + 1)^2 query pixels
    sigma: float = 1.0  # Gaussian blur (px) of the query and mapping images before aligning
    iterations: int = 15  # Gauss-Newton steps
    min_ncc: float = 0.8  # normalised cross-correlation of an alignment that is kept
    max_shift_px: float = 2.0  # an aligned keypoint moves at most this far from the detected one


def blurred_gray(img: np.ndarray, sigma: float) -> np.ndarray:
    """float32 grey image (RGB or grey input), blurred by a Gaussian of ``sigma`` px."""
    import cv2

    g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
    g = np.asarray(g, np.float32)
    return cv2.GaussianBlur(g, (0, 0), sigma) if sigma > 0 else g


class PlaneAligner:
    """Aligns a query's inlier keypoints to the mapping images of ``map_`` (a favormap Map).

    ``images``: the folder of the mapping sequence (any format favormap build reads; None: the folder
    recorded in the map's provenance). Frames are read on first use and kept, blurred grey, at the
    map's working resolution."""

    def __init__(self, map_, images: str | Path | None = None, config: AlignConfig | None = None):
        from ..triangulation import landmark_normals

        self.map = map_
        self.config = config or AlignConfig()
        self.folder = Path(images) if images is not None else None
        self._frames = None  # frame name -> (image path, camera), from the sequence, on first use
        self._images: dict[int, np.ndarray] = {}
        self.index = ObservationIndex(map_)
        positions = np.asarray(map_.positions, np.float64)
        # the plane through a landmark is the same for either sign of its normal: turned towards the
        # training cameras (the map's view_dir) only to be definite
        self.normals = landmark_normals(positions, positions + np.asarray(map_.view_dir, np.float64))
        ids = np.asarray(map_.frame_camera_ids)
        self.K = np.array([working_camera(map_.cameras[int(c)], map_.max_side).K for c in ids]).reshape(-1, 3, 3)
        # a missing or unreadable folder, or one without the map's frames, fails here, not at the first query
        missing = [n for n in map_.frame_names if n not in self._sequence_frames()]
        if missing:
            raise InputError(
                f"keypoint alignment: the mapping images lack {len(missing)} of the map's {map_.num_frames} frames "
                f"(first: {missing[0]!r})"
            )

    # -- mapping images ------------------------------------------------------------------------------
    def _sequence_frames(self) -> dict:
        if self._frames is None:
            from ..io import read_sequence

            folder = self.folder
            if folder is None:
                src = self.map.provenance.get("source")
                if not src:
                    raise InputError("the map does not record the folder it was built from: give the mapping images")
                folder = Path(src)
            if not folder.exists():
                raise InputError(f"keypoint alignment needs the map's mapping images; {folder} does not exist")
            seq = read_sequence(folder)
            self._frames = {f.name: (f.image_path, seq.cameras[f.camera_id]) for f in seq.frames}
        return self._frames

    def image(self, frame: int) -> np.ndarray:
        """Mapping frame ``frame`` (row of the map's frames), blurred grey at the map's resolution."""
        if frame not in self._images:
            from ..io import load_image

            name = self.map.frame_names[frame]
            got = self._sequence_frames()[name]
            img, cam = load_image(got[0], got[1], self.map.max_side)
            if not np.allclose(cam.K, self.K[frame], rtol=1e-4, atol=1e-3):
                raise InputError(f"keypoint alignment: the mapping image {name!r} does not match the map's camera")
            self._images[frame] = blurred_gray(img, self.config.sigma)
        return self._images[frame]

    # -- alignment -----------------------------------------------------------------------------------
    def reference_frames(self, positions: np.ndarray, rows: np.ndarray, center: np.ndarray) -> np.ndarray:
        """For each landmark of ``rows``, the mapping frame whose camera saw it from the direction
        nearest to the query camera's (``center``); -1 for a landmark without observations."""
        ix = self.index
        X = np.asarray(positions, np.float64)[np.asarray(rows, np.int64)]

        def cost(obs, group):  # minus the cosine of the angle at the landmark
            u, q = ix.centers[ix.frame[obs]] - X[group], center - X[group]
            return -np.einsum("ij,ij->i", u, q) / (np.linalg.norm(u, axis=1) * np.linalg.norm(q, axis=1) + 1e-12)

        best = ix.best(rows, cost)
        return np.where(best >= 0, ix.frame[np.maximum(best, 0)], -1)

    def align(self, gray: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray, positions, rows, keypoints):
        """Aligned positions (N, 2) of the query keypoints ``keypoints`` matched to landmarks ``rows``
        (``positions``: the localizer's landmark positions) in the query's blurred grey image ``gray``
        seen with intrinsics ``K`` from ``cam_from_world``, and which of them converged (N,)."""
        cfg = self.config
        rows = np.asarray(rows, np.int64)
        kp = np.asarray(keypoints, np.float64)
        if len(rows) == 0:
            return kp.copy(), np.zeros(0, bool)
        T = np.asarray(cam_from_world, np.float64)
        X = np.asarray(positions, np.float64)[rows]
        C = camera_centers(T)
        ref = self.reference_frames(np.asarray(positions, np.float64), rows, C)
        n = self.normals[rows]
        u0 = project(K, T, X)
        g = np.arange(-cfg.half, cfg.half + 1, dtype=np.float64)
        off = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
        u = u0[:, None, :] + off[None]  # (N, P, 2) query pixels of the template
        P = plane_points(K, T, u, X, n)  # where the template's rays meet the landmark's plane
        depth = P @ T[2, :3] + T[2, 3]
        tmpl = np.full(u.shape[:2], np.nan, np.float32)
        for f in np.unique(ref[ref >= 0]):  # one mapping frame at a time
            sel = ref == f
            uv = project(self.K[f], np.asarray(self.map.cam_from_world[f]), P[sel].reshape(-1, 3))
            tmpl[sel] = sample(self.image(int(f)), uv.reshape(-1, len(off), 2))
        ok = np.isfinite(tmpl).all(1) & (depth > 0).all(1)  # (a ray parallel to the plane: NaN)
        tmpl = np.nan_to_num(tmpl)
        gy, gx = np.gradient(gray)
        shift = np.zeros((len(rows), 2))
        gain, bias = np.ones(len(rows)), np.zeros(len(rows))
        ones = np.ones_like(tmpl)
        for _ in range(cfg.iterations):
            at = u + shift[:, None]
            val, dx, dy = sample(gray, at), sample(gx, at), sample(gy, at)
            ok &= np.isfinite(val).all(1)
            val, dx, dy = np.nan_to_num(val), np.nan_to_num(dx), np.nan_to_num(dy)
            res = val - (gain[:, None] * tmpl + bias[:, None])
            J = np.stack([dx, dy, -tmpl, -ones], -1)  # d res / d (shift, gain, bias)
            H = np.einsum("npi,npj->nij", J, J) + 1e-6 * np.eye(4)
            step = np.linalg.solve(H, -np.einsum("npi,np->ni", J, res)[..., None])[..., 0]
            shift += step[:, :2]
            gain += step[:, 2]
            bias += step[:, 3]
        val = np.nan_to_num(sample(gray, u + shift[:, None]))
        a = val - val.mean(1, keepdims=True)
        b = tmpl - tmpl.mean(1, keepdims=True)
        ncc = np.einsum("np,np->n", a, b) / np.sqrt(np.einsum("np,np->n", a, a) * np.einsum("np,np->n", b, b) + 1e-12)
        moved = u0 + shift
        ok &= np.isfinite(moved).all(1) & (ncc >= cfg.min_ncc)
        ok &= np.linalg.norm(moved - kp, axis=1) <= cfg.max_shift_px
        return np.where(ok[:, None], moved, kp), ok


def sample(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``img`` at ``xy`` (..., 2), NaN outside it."""
    return sample_bilinear(img, xy, outside=np.nan)
