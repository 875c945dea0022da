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


def pose_distances(cam_from_world: np.ndarray) -> np.ndarray:
    """(N, N) how far apart two frames' views are: the distance between their camera centres over the
    median distance of a frame to its nearest one, plus the angle between their optical axes over the
    median angle to the nearest in that sense (both 0 on the diagonal)."""
    centres = camera_centers(cam_from_world)
    axes = cam_from_world[:, 2, :3]  # each camera's optical axis in the world
    dist = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    angle = np.degrees(np.arccos(np.clip(axes @ axes.T, -1.0, 1.0)))
    off = ~np.eye(len(cam_from_world), dtype=bool)
    scale = [max(float(np.median(np.where(off, m, np.inf).min(1))), 1e-12) for m in (dist, angle)]
    return dist / scale[0] + angle / scale[1]


def path_through_poses(distance: np.ndarray) -> np.ndarray:
    """Frame indices along a greedy path: from the frame whose nearest frame is farthest (an end), each
    step to the nearest frame not yet visited."""
    n = len(distance)
    d = distance + np.diag(np.full(n, np.inf))
    order = [int(np.argmax(d.min(1)))]
    free = np.ones(n, bool)
    free[order[0]] = False
    for _ in range(n - 1):
        nxt = int(np.argmin(np.where(free, d[order[-1]], np.inf)))
        order.append(nxt)
        free[nxt] = False
    return np.array(order, np.int64)


def matching_order(cam_from_world: np.ndarray) -> np.ndarray:
    """The order tracking walks the frames in: as given (0..N-1) where consecutive frames lie near each
    other as along a path, else :func:`path_through_poses` (see MAX_STEP_RATIO)."""
    n = len(cam_from_world)
    given = np.arange(n, dtype=np.int64)
    if n < 3:
        return given
    distance = pose_distances(np.asarray(cam_from_world, np.float64))
    path = path_through_poses(distance)
    step = float(np.median(distance[given[:-1], given[1:]]))
    path_step = float(np.median(distance[path[:-1], path[1:]]))
    return path if step > MAX_STEP_RATIO * path_step else given
