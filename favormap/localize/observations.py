"""A map's observations grouped by landmark, and the per-landmark choice of one of them: the nearest
training view's descriptor (``descriptors.NearestViewDescriptors``) and the reference frame of the
keypoint alignment (``align.PlaneAligner``) both pick a landmark's observation by its camera."""

from __future__ import annotations

import numpy as np

from ..geometry import camera_centers


class ObservationIndex:
    """The observations of ``map_`` (a favormap Map) sorted by landmark, then frame: ``order`` maps a
    sorted position to the map's observation row, ``landmark`` / ``frame`` are the sorted rows,
    ``first[j]:first[j + 1]`` are landmark j's positions; ``centers`` the mapping cameras' centres;
    ``row_frame`` / ``row_xy`` each observation's frame and keypoint by the map's observation row."""

    def __init__(self, map_):
        lm, fr, xy = map_.tracks()
        self.row_frame, self.row_xy = fr, xy  # by the map's observation row
        self.order = np.lexsort((fr, lm))
        self.landmark, self.frame = lm[self.order], fr[self.order]
        self.first = np.searchsorted(self.landmark, np.arange(len(map_) + 1))
        self.centers = camera_centers(np.asarray(map_.cam_from_world))

    def of(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(sorted positions of the observations of landmarks ``rows``, grouped; each one's index in ``rows``)."""
        rows = np.asarray(rows, np.int64)
        n = self.first[rows + 1] - self.first[rows]
        obs = np.repeat(self.first[rows] - np.cumsum(n) + n, n) + np.arange(n.sum())
        return obs, np.repeat(np.arange(len(rows)), n)

    def best(self, rows: np.ndarray, cost, k: int | None = None) -> np.ndarray:
        """For each landmark of ``rows`` the sorted position of its observation of least
        ``cost(obs, group)`` (an array over ``of(rows)``'s observations); -1 for one without any.
        With ``k``: its ``k`` observations of least cost, cheapest first (len(rows), k), -1 where it
        has fewer."""
        obs, group = self.of(rows)
        out = np.full((len(np.asarray(rows)), k or 1), -1, np.int64)
        if len(obs):
            order = np.lexsort((cost(obs, group), group))
            g = group[order]
            rank = np.arange(len(g)) - np.searchsorted(g, g)  # position within its landmark's observations
            keep = rank < (k or 1)
            out[g[keep], rank[keep]] = obs[order][keep]
        return out if k else out[:, 0]
