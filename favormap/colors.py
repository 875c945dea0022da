"""The one colour ramp (viridis) for values drawn on landmarks: rerun recordings and exported meshes."""

from __future__ import annotations

import numpy as np

# viridis, 9 samples (0, 1/8, ..., 1)
VIRIDIS = np.array(
    [
        [68, 1, 84],
        [71, 44, 122],
        [59, 81, 139],
        [44, 113, 142],
        [33, 144, 141],
        [39, 173, 129],
        [92, 200, 99],
        [170, 220, 50],
        [253, 231, 37],
    ],
    np.float64,
)


def viridis(values, lo: float | None = None, hi: float | None = None) -> tuple[np.ndarray, float, float]:
    """Values -> viridis RGB uint8 (N, 3), and the ramp's ends (lo, hi). ``lo``/``hi`` default to the
    2nd/98th percentiles of the finite values; NaN takes the colour of ``lo``; when hi <= lo every
    value takes the middle colour."""
    v = np.asarray(values, np.float64).ravel()
    finite = v[np.isfinite(v)]
    if lo is None:
        lo = float(np.percentile(finite, 2)) if len(finite) else 0.0
    if hi is None:
        hi = float(np.percentile(finite, 98)) if len(finite) else 1.0
    if len(v) == 0:
        return np.zeros((0, 3), np.uint8), lo, hi
    if hi > lo:
        t = np.clip((np.nan_to_num(v, nan=lo) - lo) / (hi - lo), 0.0, 1.0)
    else:
        t = np.full(len(v), 0.5)
    x = np.linspace(0.0, 1.0, len(VIRIDIS))
    rgb = np.stack([np.interp(t, x, VIRIDIS[:, c]) for c in range(3)], 1)
    return np.round(rgb).astype(np.uint8), lo, hi
