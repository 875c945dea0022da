"""Priors for a stream of query frames from the poses already estimated (a robot's camera).

After the first frame, each frame's prior comes from the frames before it, so a sequence needs at
most one prior (or none: the first frame is then localized against all landmarks):

- ``previous``: the last localized frame's pose;
- ``constant-velocity``: that pose moved on by the motion between the last two frames, when both
  were localized one after the other (else as ``previous``).

A frame that fails does not move the prior; the next one starts again from the last localized pose
(the localizer's checks and its prior-free fallback catch a prior that has gone stale).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..geometry import inverse

MOTION_MODELS = ("previous", "constant-velocity")


@dataclass
class MotionPrior:
    """The prior of the next frame of a sequence. Call :meth:`prior` before localizing a frame and
    :meth:`update` with its result after."""

    model: str = "constant-velocity"
    first: np.ndarray | None = None  # cam_from_world prior of the first frame (None: prior-free)
    _frame: int = field(default=0, init=False)  # frames seen so far
    _last: list = field(default_factory=list, init=False)  # up to two (frame, cam_from_world) of localized frames

    def __post_init__(self):
        if self.model not in MOTION_MODELS:
            raise InputError(f"unknown motion model {self.model!r} ({', '.join(MOTION_MODELS)})")

    def prior(self) -> np.ndarray | None:
        if not self._last:
            return None if self.first is None else np.asarray(self.first, np.float64)
        k1, T1 = self._last[-1]
        if self.model == "constant-velocity" and len(self._last) == 2 and k1 == self._frame - 1:
            k0, T0 = self._last[0]
            if k0 == k1 - 1:
                step = T1 @ inverse(T0)  # cam_from_world of frame k1 = step @ that of frame k0
                return _rigid(step @ T1)
        return T1.copy()

    def update(self, result) -> None:
        """Take the result of the frame just localized (anything with ``success`` and
        ``cam_from_world``)."""
        if result.success:
            self._last = (self._last + [(self._frame, np.asarray(result.cam_from_world, np.float64))])[-2:]
        self._frame += 1


def _rigid(T: np.ndarray) -> np.ndarray:
    """T with its rotation re-orthonormalised (products of poses drift by rounding)."""
    u, _, vt = np.linalg.svd(T[:3, :3])
    out = T.copy()
    out[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out
