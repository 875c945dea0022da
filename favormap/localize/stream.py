"""Landmarks refined by a localized stream of query frames.

A landmark triangulated from a short track is well placed across its mapping rays but poorly along
them: seen from further along the path, its depth error shows as pixels, and it pulls the pose
(docs/accuracy.md, "What limits fox extrapolation"). A stream of queries sees those landmarks from
exactly there. After each localized frame, :class:`LandmarkRefinement` adds the frame's inlier
observations (its estimated pose, its keypoints) to the landmarks' mapping observations and
triangulates those landmarks again with the build's robust triangulation; the next frames are
localized against the refined positions.

- Only landmarks the frame sees as uncertain take its observations: those whose map covariance
  (favormap.localize.refine.landmark_covariances), projected into the frame, has a standard
  deviation of at least ``min_uncertainty_px`` (0.25 px). Landmarks the map already places well
  would only take on the frame's own pose error (docs/accuracy.md).
- Only the geometry moves (visibility, projections, PnP): the voxel grids stay where they were
  trained, and a refined position that leaves its landmark's voxel box by more than
  ``max_move`` box sides is not taken (a wrong match cannot drag a landmark away).
- Each landmark keeps its latest ``max_observations`` stream observations, so the work per frame
  grows with the landmarks it sees, not with the length of the stream.
- Nothing is written to the map; :meth:`LandmarkRefinement.close` gives the localizer back the
  map's positions.
"""

from __future__ import annotations

import numpy as np

from ..io.images import working_camera
from ..tracking import Tracks
from ..triangulation import TriangulationConfig, triangulate
from .motion import MotionPrior

# Levenberg-Marquardt iterations of each frame's re-triangulation (the build's: 15). After 5 the robust cost is
# within ~0.6 % of its value after 15 (median over a TUM stream's frames), and the streams localize alike query
# by query (docs/measurements.md) in 50 ms less per frame
REFINE_ITERATIONS = 5


class Stream:
    """The state of a stream of frames localized one after the other: the next frame's prior
    (:class:`~favormap.localize.motion.MotionPrior`) and, with ``refine_landmarks``, the landmarks
    refined from the frames localized so far (:class:`LandmarkRefinement`). :meth:`prior` before a
    frame, :meth:`update` with its result after, :meth:`close` at the end (also as a context manager)."""

    def __init__(self, localizer, first_prior=None, motion: str = "constant-velocity", refine_landmarks: bool = True):
        self.motion = MotionPrior(motion, first_prior)
        self.refinement = LandmarkRefinement(localizer) if refine_landmarks else None

    def prior(self):
        return self.motion.prior()

    def update(self, result) -> np.ndarray:
        """Take a frame's result; returns the landmark rows it refined."""
        refine = self.update_later(result)
        return np.zeros(0, np.int64) if refine is None else refine()

    def update_later(self, result):
        """:meth:`update` in two parts: the motion prior now, the landmark refinement returned (a callable, or
        None) for the caller to run before the next frame uses the landmarks' positions (the localizer runs it
        while that frame's features are extracted)."""
        self.motion.update(result)
        if self.refinement is None:
            return None
        return lambda: self.refinement.update(result)

    def close(self) -> None:
        if self.refinement is not None:
            self.refinement.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class Retriangulation:
    """Points re-triangulated from their mapping observations plus those of a stream of localized
    frames (the core of :class:`LandmarkRefinement` and of the structure baseline's
    :class:`favormap.localize.baseline.PointRefinement`).

    ``positions`` (P, 3) is updated in place; ``obs_point`` / ``obs_frame`` / ``obs_xy``: the mapping
    observations (point, frame, pixel) in the frames ``cam_from_world`` (F, 4, 4) with intrinsics
    ``Ks`` (F, 3, 3); ``max_move`` (P,): how far (world units) a refined point may be from its
    starting position, or it is not taken."""

    def __init__(
        self, positions, obs_point, obs_frame, obs_xy, cam_from_world, Ks, max_move, max_observations: int = 10
    ):
        self.positions = positions
        self.start = np.array(positions, np.float64, copy=True)  # where the map put the points
        self.max_move = np.asarray(max_move, np.float64).reshape(-1)
        self.max_observations = int(max_observations)
        order = np.argsort(obs_point, kind="stable")
        self._map_obs = (
            np.asarray(obs_point)[order],
            np.asarray(obs_frame)[order],
            np.asarray(obs_xy, np.float64)[order],
        )
        self._offsets = np.searchsorted(self._map_obs[0], np.arange(len(positions) + 1))
        self._frames = np.asarray(cam_from_world, np.float64)
        self._K = np.asarray(Ks, np.float64)
        self._poses: list[np.ndarray] = []  # stream frames that gave observations
        self._Ks: list[np.ndarray] = []
        # stream observations: point, stream frame, keypoint (px); each point's latest max_observations
        self._s_pt = np.zeros(0, np.int64)
        self._s_frame = np.zeros(0, np.int64)
        self._s_xy = np.zeros((0, 2))
        self.frames_used = 0
        self.updates = 0  # point positions taken
        self.refused = 0  # refined positions beyond max_move, not taken

    def add(self, cam_from_world, K, points, xy) -> np.ndarray:
        """Take one localized frame's observations (``points`` (N,) seen at pixels ``xy`` (N, 2)),
        triangulate those points again; returns the rows whose positions moved."""
        points = np.asarray(points, np.int64).reshape(-1)
        if not len(points):
            return np.zeros(0, np.int64)
        s = len(self._poses)
        self._poses.append(np.asarray(cam_from_world, np.float64))
        self._Ks.append(np.asarray(K, np.float64))
        self.frames_used += 1
        pt = np.concatenate([self._s_pt, points])
        fr = np.concatenate([self._s_frame, np.full(len(points), s, np.int64)])
        xy = np.concatenate([self._s_xy, np.asarray(xy, np.float64).reshape(-1, 2)])
        # each point keeps its latest max_observations
        order = np.lexsort((-fr, pt))
        pt_sorted = pt[order]
        first = np.searchsorted(pt_sorted, pt_sorted, side="left")
        keep = np.sort(order[np.arange(len(order)) - first < self.max_observations])
        self._s_pt, self._s_frame, self._s_xy = pt[keep], fr[keep], xy[keep]
        return self._retriangulate(np.unique(points))

    def _retriangulate(self, rows: np.ndarray) -> np.ndarray:
        tl, tf, txy = self._map_obs
        nF = len(self._frames)
        starts, ends = self._offsets[rows], self._offsets[rows + 1]
        counts = ends - starts
        mi = np.repeat(starts - np.cumsum(counts) + counts, counts) + np.arange(counts.sum())  # their mapping obs
        si = np.flatnonzero(np.isin(self._s_pt, rows))  # their stream obs
        used, s_frame = np.unique(self._s_frame[si], return_inverse=True)
        frame = np.concatenate([tf[mi], nF + s_frame])
        xy = np.concatenate([txy[mi], self._s_xy[si]])
        tid = np.concatenate([tl[mi], self._s_pt[si]])
        tracks = Tracks.from_obs(frame, np.zeros(len(frame), np.int32), xy, tid)  # track j <-> rows[j]
        poses = np.concatenate([self._frames, np.stack([self._poses[f] for f in used])])
        Ks = np.concatenate([self._K, np.stack([self._Ks[f] for f in used])])
        lms = triangulate(tracks, poses, Ks, TriangulationConfig(min_track=2, iterations=REFINE_ITERATIONS))
        pt_rows = rows[lms.source]
        move = np.linalg.norm(lms.positions - self.start[pt_rows], axis=1)
        ok = np.isfinite(move) & (move <= self.max_move[pt_rows])
        self.positions[pt_rows[ok]] = lms.positions[ok]
        self.updates += int(ok.sum())
        self.refused += int((~ok).sum())
        return pt_rows[ok]


class LandmarkRefinement:
    """Refines ``localizer``'s landmark positions (a copy of the map's) from the frames given to
    :meth:`update`, in order."""

    def __init__(self, localizer, max_observations: int = 10, max_move: float = 0.5, min_uncertainty_px: float = 0.25):
        self.localizer = localizer
        m = localizer.map
        self.positions = np.array(m.positions, np.float64)
        self.min_uncertainty_px = float(min_uncertainty_px)
        tl, tf, txy = m.tracks()
        Ks = np.stack([working_camera(m.cameras[int(c)], m.max_side).K for c in m.frame_camera_ids])
        box = np.asarray(m.voxel_size, np.float64).reshape(-1)
        self.core = Retriangulation(
            self.positions, tl, tf, txy, m.cam_from_world, Ks, float(max_move) * box, max_observations
        )
        localizer.positions = self.positions

    map_positions = property(lambda self: self.core.start)  # where the map put them: the voxel boxes' centres
    frames_used = property(lambda self: self.core.frames_used)
    updates = property(lambda self: self.core.updates)  # landmark positions taken
    refused = property(lambda self: self.core.refused)  # refined positions outside the landmark's box

    def close(self) -> None:
        """Give the localizer back the map's own positions."""
        self.localizer.positions = self.localizer.map.positions

    def update(self, result) -> np.ndarray:
        """Take a frame's result; returns the rows whose positions moved (none when it failed)."""
        if not result.success or result.matches is None or result.inlier_mask is None or result.camera is None:
            return np.zeros(0, np.int64)
        inl = np.asarray(result.matches, np.int64)[np.asarray(result.inlier_mask, bool)]
        if len(inl) and self.min_uncertainty_px > 0:  # only landmarks this frame sees as uncertain
            inl = inl[self._projected_std(inl[:, 0], result) >= self.min_uncertainty_px]
        kp = np.asarray(result.keypoints, np.float64)
        return self.core.add(result.image_cam_from_world, result.camera.K, inl[:, 0], kp[inl[:, 1]])

    def _projected_std(self, rows: np.ndarray, result) -> np.ndarray:
        """Largest standard deviation (px) of the map's position covariance of landmarks ``rows``
        projected into the frame of ``result``."""
        from .refine import projected_std

        cov = self.localizer._landmark_covariances(rows)
        return projected_std(self.positions[rows], cov, result.image_cam_from_world, result.camera.K)
