"""OpenCV SIFT's pyramid arithmetic (numpy only): where a keypoint of a given size sits in the
scale space, and what OpenCV's packed octave means. Shared by :mod:`favormap.features.sift` (OpenCV,
never imports torch) and :mod:`favormap.features.sift_torch` (the same descriptors in torch)."""

from __future__ import annotations

import numpy as np

# nOctaveLayers and sigma of cv2.SIFT_create's defaults (used to place a size in the pyramid)
LAYERS, SIGMA = 3, 1.6


def min_response(contrast_threshold: float) -> float:
    """The smallest keypoint response OpenCV keeps at ``contrast_threshold`` (it drops an extremum
    whose |DoG| * nOctaveLayers is below the threshold): the keypoints of an extraction at a lower
    threshold with at least this response are those an extraction at this one finds."""
    return contrast_threshold / LAYERS


def unpack_octave(packed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """OpenCV's ``unpackOctave``: octave (-1 for the upsampled first one), layer, and the scale from
    image pixels to the octave's pixels (float32), of packed octaves (octave & 255 | layer << 8)."""
    packed = np.asarray(packed, np.int64)
    octave = packed & 255
    octave = np.where(octave < 128, octave, octave - 256)
    scale = np.where(octave >= 0, 1.0 / (1 << np.maximum(octave, 0)), 2.0 ** np.maximum(-octave, 0))
    return octave, (packed >> 8) & 255, scale.astype(np.float32)


def octave_of_size(size: np.ndarray) -> np.ndarray:
    """OpenCV's packed octave (octave & 255 | layer << 8) of keypoints of diameter ``size`` (px):
    the inverse of detection's size = 2 sigma 2^(octave + layer / nOctaveLayers)."""
    total = np.log2(np.maximum(np.asarray(size, np.float64), 1e-6) / (2 * SIGMA)) * LAYERS
    octave = np.floor((total - 0.5) / LAYERS).astype(np.int64)
    layer = np.clip(np.round(total - LAYERS * octave), 1, LAYERS).astype(np.int64)
    octave = np.maximum(octave, -1)
    return (octave & 255) | (layer << 8)
