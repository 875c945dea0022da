"""frame_order: the order in which tracking walks the frames (each frame is matched with its next
``window`` ones in it).

A video, a robot's log or a walk around an object lists its frames along the camera's path, and the
next frames in that order reach a few frames' baseline away: tracks link wider baselines than a
frame's nearest poses alone would give. A folder that lists its frames in no such order (photos of
several walks, an export sorted by an unrelated key) is walked along a path through the poses
instead: nearest neighbour by nearest neighbour, from one end.
"""

from __future__ import annotations

import numpy as np

from .geometry import camera_centers

# the given order is kept unless its median step between consecutive frames is more than this many times
# the median step of the path through the poses (videos and captures listed by name: at most 1.5; the
# same frames shuffled: 2.3 to 18 on the accuracy suite's sets)
MAX_STEP_RATIO = 2.0


def pose_points(cam_from_world: np.ndarray) -> np.ndarray:
    """(N, 6) each frame's view as a point: its camera centre over the median distance of a frame's centre
    to its nearest one, beside its optical axis over the median distance of an axis to its nearest one (for
    near axes the angle between them), so that nearby points are frames that see nearly the same."""
    from scipy.spatial import cKDTree

    T = np.asarray(cam_from_world, np.float64)
    parts = [camera_centers(T), T[:, 2, :3]]  # centres and optical axes in the world
    out = []
    for p in parts:
        nearest = cKDTree(p).query(p, k=2)[0][:, 1] if len(p) > 1 else np.ones(1)
        positive = nearest[nearest > 0]
        out.append(p / (float(np.median(positive)) if len(positive) else 1.0))
    return np.hstack(out)


def path_through_poses(points: np.ndarray) -> np.ndarray:
    """Frame indices along a greedy path through ``points`` (:func:`pose_points`): from the frame whose
    nearest frame is farthest (an end), each step to the nearest frame not yet visited."""
    from scipy.spatial import cKDTree

    n = len(points)
    if n < 3:
        return np.arange(n, dtype=np.int64)
    tree = cKDTree(points)
    order = [int(np.argmax(tree.query(points, k=2)[0][:, 1]))]
    free = np.ones(n, bool)
    free[order[0]] = False
    for _ in range(n - 1):
        k = 8
        while True:  # the nearest frames until one is not yet visited
            _, near = tree.query(points[order[-1]], k=min(k, n))
            near = np.atleast_1d(near)
            unvisited = near[free[near]]
            if len(unvisited) or k >= n:
                break
            k *= 4
        order.append(int(unvisited[0]))
        free[order[-1]] = False
    return np.array(order, np.int64)


def matching_order(cam_from_world: np.ndarray) -> np.ndarray:
    """The order tracking walks the frames in: as given (0..N-1) where consecutive frames lie near each
    other as along a path, else :func:`path_through_poses` (see MAX_STEP_RATIO)."""
    n = len(cam_from_world)
    given = np.arange(n, dtype=np.int64)
    if n < 3:
        return given
    points = pose_points(cam_from_world)
    path = path_through_poses(points)

    def median_step(order):
        return float(np.median(np.linalg.norm(np.diff(points[order], axis=0), axis=1)))

    return path if median_step(given) > MAX_STEP_RATIO * median_step(path) else given
