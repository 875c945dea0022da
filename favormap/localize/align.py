"""Query keypoints aligned to the mapping images through each landmark's local plane.

A SIFT keypoint's position moves with the view: where a blob is detected on a slanted textured
surface shifts by a fraction of a pixel as the camera moves round it, and the inliers of one query,
seen from one side, shift alike, which moves the pose (docs/accuracy.md). This stage replaces each
inlier's detected keypoint, before the final weighted
refinement, by where the landmark's appearance in a mapping image lies in the query: the query's
``(2h+1)^2`` pixels around the landmark's predicted projection are carried through the plane through
the landmark (normal from its nearest landmarks, :func:`favormap.triangulation.landmark_normals`)
into the mapping frame that saw the landmark from the nearest direction, and a Lucas-Kanade
alignment (2D shift, gain and offset; PTAM / SVO-style feature alignment) finds the shift in the
query that matches that template best. The alignment is kept where it converged (normalised
cross-correlation >= ``min_ncc``) within ``max_shift_px`` of the detected keypoint.

It needs the mapping images: the grey pixels around each observation that a map built with
``favormap build --align-patches RADIUS`` stores (``tracks/patch``), or else the folder the map was built
from (its provenance), or another folder of the same sequence. Both give the same alignment (the
stored pixels are the image's, blurred alike) wherever the template's footprint in the mapping frame
lies inside the stored patch less the blur's reach; where it does not, the detected keypoint stays.

It helps where the mapping poses are exact (a map built with ``favormap build --exact-poses``, whose
tracks are aligned the same way) and where the detector places keypoints imprecisely (DISK, ALIKED), and
costs a little where SfM poses carry errors of their own (SIFT maps of real captures): so it is on by
default for the maps whose build asks for it (their provenance records it, ``build.localize_defaults``)
and off for SIFT maps; docs/accuracy.md has the figures. Aligned to one mapping frame, a keypoint
inherits that frame's pose error; ``AlignConfig.references`` > 1 aligns it to several frames nearest in
direction, each alone, and averages the converged results.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry import camera_centers, plane_points, project
from ..io.images import sample_bilinear, working_camera
from .observations import ObservationIndex

PATCH_BLOCK = 1024  # observations whose stored patches are read together (~1.7 MB at 41 x 41)


@dataclass(frozen=True)
class AlignConfig:
    half: int = 5  # template of (2 half + 1)^2 query pixels
    sigma: float = 1.0  # Gaussian blur (px) of the query and mapping images before aligning
    iterations: int = 15  # Gauss-Newton steps
    min_ncc: float = 0.8  # normalised cross-correlation of an alignment that is kept
    max_shift_px: float = 2.0  # an aligned keypoint moves at most this far from the detected one
    # mapping frames aligned to per landmark, nearest in direction first; the converged alignments
    # are averaged, which averages the mapping poses' errors too
    references: int = 1


def blurred_gray(img: np.ndarray, sigma: float) -> np.ndarray:
    """float32 grey image (RGB or grey input), blurred by a Gaussian of ``sigma`` px."""
    import cv2

    g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
    g = np.asarray(g, np.float32)
    return cv2.GaussianBlur(g, (0, 0), sigma) if sigma > 0 else g


class PlaneAligner:
    """Aligns a query's inlier keypoints to the mapping images of ``map_`` (a favormap Map).

    ``images``: the folder of the mapping sequence (any format favormap build reads); None: the
    observation patches the map stores (``Map.has_track_patches``), else the folder recorded in the
    map's provenance. Frames are read on first use and kept, blurred grey, at the map's working
    resolution; stored patches are read for the landmarks of each query."""

    def __init__(self, map_, images: str | Path | None = None, config: AlignConfig | None = None):
        from ..triangulation import landmark_normals

        self.map = map_
        self.config = config or AlignConfig()
        self.folder = Path(images) if images is not None else None
        # the map's own patches unless a folder is given
        self.from_patches = images is None and bool(getattr(map_, "has_track_patches", False))
        self._frames = None  # frame name -> (image path, camera), from the sequence, on first use
        self._images: dict[int, np.ndarray] = {}
        self.index = ObservationIndex(map_)
        positions = np.asarray(map_.positions, np.float64)
        # the plane through a landmark is the same for either sign of its normal: turned towards the
        # training cameras (the map's view_dir) only to be definite
        self.normals = landmark_normals(positions, positions + np.asarray(map_.view_dir, np.float64))
        ids = np.asarray(map_.frame_camera_ids)
        cams = [working_camera(map_.cameras[int(c)], map_.max_side) for c in ids]
        self.K = np.array([c.K for c in cams]).reshape(-1, 3, 3)
        self.sizes = np.array([(c.width, c.height) for c in cams], np.int64).reshape(-1, 2)
        self.obs_frame, self.xy = self.index.row_frame, self.index.row_xy  # by observation row: frame, patch centre
        if self.from_patches:
            # the stored patches, read block by block as the queries need them (pages of the array
            # never written cost no memory)
            side = 2 * map_.track_patch_radius + 1
            self._patches = np.empty((len(self.xy), side, side), np.uint8)
            self._read = np.zeros(-(-len(self.xy) // PATCH_BLOCK), bool)
            return
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
    def reference_observations(
        self, positions: np.ndarray, rows: np.ndarray, center: np.ndarray, k: int | None = None
    ) -> np.ndarray:
        """For each landmark of ``rows``, the map's observation row whose camera saw it from the
        direction nearest to the query camera's (``center``); -1 for a landmark without observations.
        With ``k``: its ``k`` nearest in direction (len(rows), k), -1 where it has fewer."""
        ix = self.index
        X = np.asarray(positions, np.float64)[np.asarray(rows, np.int64)]

        def cost(obs, group):  # minus the cosine of the angle at the landmark
            u, q = ix.centers[ix.frame[obs]] - X[group], center - X[group]
            return -np.einsum("ij,ij->i", u, q) / (np.linalg.norm(u, axis=1) * np.linalg.norm(q, axis=1) + 1e-12)

        best = ix.best(rows, cost, k)
        return np.where(best >= 0, ix.order[np.maximum(best, 0)], -1)

    def reference_frames(self, positions: np.ndarray, rows: np.ndarray, center: np.ndarray) -> np.ndarray:
        """For each landmark of ``rows``, the mapping frame of :meth:`reference_observations` (or -1)."""
        obs = self.reference_observations(positions, rows, center)
        return np.where(obs >= 0, self.obs_frame[np.maximum(obs, 0)], -1)

    def templates(self, P: np.ndarray, obs: np.ndarray) -> np.ndarray:
        """The blurred grey values (N, n) of the mapping images at the 3D points ``P`` (N, n, 3), each
        row seen in the frame of its observation ``obs`` (N,; -1: NaN): from the frames' images, or
        from the stored patches (NaN where a point falls outside the part of its patch the blur
        reaches exactly)."""
        out = np.full(P.shape[:2], np.nan, np.float32)
        frames = np.where(obs >= 0, self.obs_frame[np.maximum(obs, 0)], -1)
        has = np.flatnonzero(obs >= 0)
        if not len(has):
            return out
        uv = np.empty(P.shape[:2] + (2,))
        for f in np.unique(frames[has]):  # one mapping frame at a time
            sel = np.flatnonzero(frames == f)
            uv[sel] = project(self.K[f], np.asarray(self.map.cam_from_world[f]), P[sel].reshape(-1, 3)).reshape(
                len(sel), -1, 2
            )
            if not self.from_patches:
                out[sel] = sample(self.image(int(f)), uv[sel])
        if self.from_patches:
            out[has] = self._patch_samples(obs[has], frames[has], uv[has])
        return out

    def patches(self, obs: np.ndarray) -> np.ndarray:
        """The stored grey patches (n, P, P) of observation rows ``obs``."""
        for b in np.unique(np.asarray(obs, np.int64) // PATCH_BLOCK):
            if not self._read[b]:
                a = b * PATCH_BLOCK
                self._patches[a : a + PATCH_BLOCK] = self.map.track_patches(slice(a, a + PATCH_BLOCK))
                self._read[b] = True
        return self._patches[obs]

    def _patch_samples(self, obs: np.ndarray, frames: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Samples at frame pixels ``uv`` (N, n, 2) of the stored patches of observations ``obs``: the
        patches tiled into one image and blurred together; the tiles' rims the blur mixes, and the
        pixels beyond the frame's edge (NaN in the image path), masked."""
        import cv2

        patches = self.patches(obs).astype(np.float32)
        n, S = len(obs), patches.shape[1]
        R = (S - 1) // 2
        w, h = self.sizes[frames, 0, None], self.sizes[frames, 1, None]
        # frame pixel of each patch's (0, 0): as io.images.patches_around cut it
        corner = np.clip(np.floor(self.xy[obs].astype(np.float64)), 0, np.concatenate([w, h], 1) - 1) - R
        g = np.arange(S)
        col, row = corner[:, 0, None] + g, corner[:, 1, None] + g  # frame pixel coordinates of the tiles
        sigma = self.config.sigma
        rim = (int(round(sigma * 8 + 1)) | 1) // 2 if sigma > 0 else 0  # cv2.GaussianBlur's kernel radius (float)
        inner = (g >= rim) & (g < S - rim)
        ok_c, ok_r = inner & (col >= 0) & (col < w), inner & (row >= 0) & (row < h)
        cols = int(np.ceil(np.sqrt(n)))
        mosaic = _mosaic(patches, cols)
        if sigma > 0:
            mosaic = cv2.GaussianBlur(mosaic, (0, 0), sigma)
        mosaic[_mosaic(ok_r[:, :, None] & ok_c[:, None, :], cols) == 0] = np.nan
        at = uv - corner[:, None, :] + S * np.stack([np.arange(n) % cols, np.arange(n) // cols], -1)[:, None, :]
        return sample(mosaic, at)

    def align(self, gray: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray, positions, rows, keypoints):
        """Aligned positions (N, 2) of the query keypoints ``keypoints`` matched to landmarks ``rows``
        (``positions``: the localizer's landmark positions) in the query's blurred grey image ``gray``
        seen with intrinsics ``K`` from ``cam_from_world``, and which of them converged (N,)."""
        rows = np.asarray(rows, np.int64)
        kp = np.asarray(keypoints, np.float64)
        if len(rows) == 0:
            return kp.copy(), np.zeros(0, bool)
        T = np.asarray(cam_from_world, np.float64)
        k = max(1, int(self.config.references))
        ref = self.reference_observations(np.asarray(positions, np.float64), rows, camera_centers(T), k)
        # every (landmark, reference) pair aligned alone (a landmark with fewer than k observations has
        # fewer pairs); a landmark's converged ones averaged
        ref = ref.ravel()
        pair = ref >= 0
        moved, ok = np.repeat(kp, k, 0), np.zeros(len(ref), bool)
        if pair.any():
            lm = np.repeat(rows, k)[pair]
            moved[pair], ok[pair] = self._align_pairs(gray, K, T, positions, lm, ref[pair], moved[pair])
        ok = ok.reshape(-1, k)
        n_ok = ok.sum(1)
        mean = np.where(ok[..., None], moved.reshape(-1, k, 2), 0.0).sum(1) / np.maximum(n_ok, 1)[:, None]
        return np.where(n_ok[:, None] > 0, mean, kp), n_ok > 0

    def _align_pairs(self, gray, K, T, positions, rows, ref, kp):
        """:meth:`align` of each landmark of ``rows`` to its reference observation ``ref`` (-1: none):
        positions (N, 2) and which converged (N,)."""
        cfg = self.config
        X = np.asarray(positions, np.float64)[rows]
        n = self.normals[rows]
        u0 = project(K, T, X)
        g = np.arange(-cfg.half, cfg.half + 1, dtype=np.float64)
        off = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
        u = u0[:, None, :] + off[None]  # (N, P, 2) query pixels of the template
        P = plane_points(K, T, u, X, n)  # where the template's rays meet the landmark's plane
        depth = P @ T[2, :3] + T[2, 3]
        tmpl = self.templates(P, ref)
        ok = np.isfinite(tmpl).all(1) & (depth > 0).all(1)  # (a ray parallel to the plane: NaN)
        tmpl = np.nan_to_num(tmpl)
        gy, gx = np.gradient(gray)
        # the image and its gradients as one 3-channel image: one bilinear lookup a step for all three
        stack = np.ascontiguousarray(np.stack([gray, gx, gy], -1), np.float32)
        shift = np.zeros((len(rows), 2))
        gain, bias = np.ones(len(rows)), np.zeros(len(rows))
        ones = np.ones_like(tmpl)
        for _ in range(cfg.iterations):
            vd = sample(stack, u + shift[:, None])  # (N, P, 3): value, d/dx, d/dy
            ok &= np.isfinite(vd[..., 0]).all(1)
            vd = np.nan_to_num(vd)
            res = vd[..., 0] - (gain[:, None] * tmpl + bias[:, None])
            J = np.stack([vd[..., 1], vd[..., 2], -tmpl, -ones], -1)  # d res / d (shift, gain, bias)
            Jt = J.transpose(0, 2, 1)
            H = Jt @ J + 1e-6 * np.eye(4)  # batched products: BLAS, not einsum's loops
            step = np.linalg.solve(H, -(Jt @ res[..., None]))[..., 0]
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


def _mosaic(tiles: np.ndarray, cols: int) -> np.ndarray:
    """Tiles (n, S, S) laid out as one image, ``cols`` tiles a row, tile i at row i // cols (zeros after the last)."""
    n, S = len(tiles), tiles.shape[1]
    rows = -(-n // cols)
    grid = np.zeros((rows * cols, S, S), np.float32)
    grid[:n] = tiles
    return grid.reshape(rows, cols, S, S).transpose(0, 2, 1, 3).reshape(rows * S, cols * S)


def sample(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``img`` at ``xy`` (..., 2), NaN outside it."""
    return sample_bilinear(img, xy, outside=np.nan)
