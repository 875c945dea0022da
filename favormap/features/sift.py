"""OpenCV SIFT (128 channels, no weights), RootSIFT-normalised.

Keypoints are detected and described in one pass, each in its own scale, orientation and pyramid
level (octave and layer), as in any SIFT pipeline (the structure baseline, COLMAP). To sample
descriptors at arbitrary positions (the S x S training patches around a landmark's observation), a
point takes the scale, orientation and pyramid level of the nearest detected keypoint within
``support_px`` pixels (so a patch around a keypoint is described in that keypoint's frame and
matches it), and a fixed upright ``size`` at the pyramid level of that size elsewhere. On a
``device`` other than the CPU, :meth:`SIFTExtractor.sample` computes OpenCV's descriptors in torch
there (:mod:`favormap.features.sift_torch`, ``torch_descriptors``); detection is always OpenCV's.

Describing a keypoint at its own pyramid level instead of the first one (what OpenCV's ``compute``
does with keypoints that carry no octave) keeps the descriptor scale-invariant (more correct matches
between frames far apart: docs/implementation-notes.md), and takes one pass instead of two per query
image."""

from __future__ import annotations

import cv2
import numpy as np

from .base import Extractor, ExtractorPolicy, Features, register
from .sift_octave import SIGMA, octave_of_size, unpack_octave


class _SiftState:
    """What :meth:`SIFTExtractor.sample` needs of an image: the grey image and its keypoints'
    positions (COLMAP convention), OpenCV sizes, angles (deg) and packed octaves (octave & 255 |
    layer << 8). A localizer never samples, so the sizes, angles and octaves are read from the
    OpenCV keypoints on first use (reading cv2.KeyPoint attributes costs ~1 us each, ~5 ms per
    4,096-keypoint query)."""

    def __init__(self, gray, xy, size=None, angle=None, octave=None, keypoints=None):
        self.gray, self.xy = gray, xy
        self._size, self._angle, self._octave = size, angle, octave
        self._keypoints = keypoints  # the kept cv2.KeyPoints, in the order of xy

    def _read(self):
        if self._size is None:
            kp = self._keypoints or ()
            self._size = np.fromiter((k.size for k in kp), np.float32, len(kp))
            self._angle = np.fromiter((k.angle for k in kp), np.float32, len(kp))
            self._octave = np.fromiter((k.octave for k in kp), np.int64, len(kp))
            self._keypoints = None

    def __getstate__(self):  # pickling (Ray tasks, process pools): arrays only, cv2.KeyPoint does not pickle
        self._read()
        return dict(self.__dict__)

    @property
    def size(self) -> np.ndarray:  # (N,) OpenCV keypoint size
        self._read()
        return self._size

    @property
    def angle(self) -> np.ndarray:  # (N,) OpenCV keypoint angle (deg)
        self._read()
        return self._angle

    @property
    def octave(self) -> np.ndarray:  # (N,) OpenCV's packed octave / layer of each keypoint
        self._read()
        return self._octave


# OpenCV's contrast threshold (its default 0.04 halved: more keypoints on low-texture surfaces); maps
# and their queries are extracted with it
CONTRAST_THRESHOLD = 0.02
# a keypoint on the upsampled first octave (-1, layer 1): added to every compute() call so that
# OpenCV always builds the pyramid from the upsampled image, as detection does, and a descriptor
# does not depend on which other points are described with it
_ANCHOR_OCTAVE = (-1 & 255) | (1 << 8)


@register("sift")
class SIFTExtractor(Extractor):
    channels = 128
    samples_on_device = True
    # A keypoint's descriptor takes the scale and orientation of the keypoint detected nearest to it, so
    # beyond ~10 deg from the training views the track's mean predicts it better than the nearest view;
    # describing one point at a time is half of a build, so the training patches are described on a
    # sub-grid; the closed-form "balanced" training suits the descriptor's smooth view dependence.
    policy = ExtractorPolicy(training_quality="balanced", view_prior_deg=10.0, patch_interp=True, match_ratio=0.9)

    def __init__(
        self,
        max_keypoints: int = 2048,
        device: str | None = None,
        size: float = 12.0,
        support_px: float = 4.0,
        orientations: str = "strongest",
        contrast_threshold: float = CONTRAST_THRESHOLD,
        torch_descriptors: bool | None = None,
    ):
        super().__init__(max_keypoints, device)
        # sample() through favormap.features.sift_torch (OpenCV's descriptors computed by torch on
        # ``device``) instead of OpenCV: None, on any device but the CPU (where OpenCV is faster)
        self.torch_descriptors = str(self.device) != "cpu" if torch_descriptors is None else bool(torch_descriptors)
        self.size = float(size)
        self.support_px = float(support_px)
        # OpenCV gives a location one keypoint per dominant orientation (peaks within 80 % of the
        # highest): "strongest" keeps the strongest one (one track node per location), "all" keeps them all
        if orientations not in ("strongest", "all"):
            raise ValueError(f"orientations must be 'strongest' or 'all', not {orientations!r}")
        self.orientations = orientations
        if not (isinstance(contrast_threshold, (int, float)) and 0 < contrast_threshold < float("inf")):
            raise ValueError(f"contrast_threshold must be a number > 0, not {contrast_threshold!r}")
        self.contrast_threshold = float(contrast_threshold)
        # nfeatures=0: OpenCV returns every keypoint and extract() keeps the strongest max_keypoints itself.
        # OpenCV's own cap (KeyPointsFilter.retainBest, an nth_element) reorders keypoints of equal
        # response, and the orientations OpenCV finds at one location all share its response, so which
        # one a cap keeps depends on how many keypoints the whole image has. Uncapped, it is the
        # first of OpenCV's orientation histogram peaks: a function of the location's own appearance,
        # the same in a map and a query
        self._sift = cv2.SIFT_create(nfeatures=0, contrastThreshold=self.contrast_threshold)

    def extract(self, image: np.ndarray) -> Features:
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        kps, desc = self._sift.detectAndCompute(gray, None)
        if desc is None or not len(kps):
            kps, desc = (), np.zeros((0, 128), np.float32)
        xy = cv2.KeyPoint_convert(kps).reshape(-1, 2) if len(kps) else np.zeros((0, 2), np.float32)
        response = np.fromiter((k.response for k in kps), np.float32, len(kps))
        order = np.argsort(-response, kind="stable")[: self.max_keypoints]
        if self.orientations == "all":
            uniq = order
        else:  # several detections at one position (different orientations): keep the strongest
            q = np.round(xy[order].astype(np.float64) * 10).astype(np.int64)  # positions to 0.1 px
            _, first = np.unique((q[:, 0] << 32) + q[:, 1], return_index=True)
            uniq = order[np.sort(first)]
        state = _SiftState(gray, xy[uniq] + 0.5, keypoints=[kps[i] for i in uniq])
        return Features(state.xy, response[uniq], _root_sift(desc[uniq]), (image.shape[1], image.shape[0]), state)

    @classmethod
    def state_arrays(cls, state: _SiftState) -> dict[str, np.ndarray]:
        return {k: getattr(state, k) for k in ("gray", "xy", "size", "angle", "octave")}

    @classmethod
    def state_from_arrays(cls, arrays: dict[str, np.ndarray]) -> _SiftState:
        return _SiftState(*(arrays[k] for k in ("gray", "xy", "size", "angle", "octave")))

    def sample(self, features: Features, points: np.ndarray) -> np.ndarray:
        st: _SiftState = features.dense
        pts = np.asarray(points, np.float32).reshape(-1, 2)
        size = np.full(len(pts), self.size, np.float32)
        angle = np.zeros(len(pts), np.float32)
        octave = np.full(len(pts), int(octave_of_size(self.size)), np.int64)
        finite = np.isfinite(pts).all(axis=1)  # NaN / inf points: never near a keypoint
        if finite.any() and len(st.xy):
            from scipy.spatial import cKDTree  # not torch: creating and using SIFT never imports torch

            dist, nn = cKDTree(st.xy.astype(np.float64)).query(pts[finite].astype(np.float64), k=1)
            near = np.zeros(len(pts), bool)
            near[finite] = dist <= self.support_px
            nn = nn[near[finite]]
            size[near], angle[near], octave[near] = st.size[nn], st.angle[nn], st.octave[nn]
        return self._describe(st, pts, size, angle, octave)

    def _describe(
        self, st: _SiftState, pts: np.ndarray, size: np.ndarray, angle: np.ndarray, octave: np.ndarray
    ) -> np.ndarray:
        if len(pts) == 0:
            return np.zeros((0, 128), np.float32)
        h, w = st.gray.shape
        p = np.asarray(pts, np.float32) - 0.5
        p[:, 0] = np.clip(p[:, 0], 0, w - 1)
        p[:, 1] = np.clip(p[:, 1], 0, h - 1)
        # each distinct descriptor once (the patch points of neighbouring observations coincide), then spread
        first, inverse = _distinct(p, size, angle, octave)
        p, size, angle, octave = p[first], size[first], angle[first], octave[first]
        if self.torch_descriptors:  # the same descriptors, computed by torch on the device (a build's patches)
            from . import sift_torch

            return _root_sift(sift_torch.describe(st.gray, p, size, angle, octave, self.device))[inverse]
        # from Python lists: NumPy scalars converted one by one took 2.6x as long (~3 us per point, under the GIL)
        kps = [
            cv2.KeyPoint(x, y, s, a, 0, o)
            for x, y, s, a, o in zip(p[:, 0].tolist(), p[:, 1].tolist(), size.tolist(), angle.tolist(), octave.tolist())
        ]
        anchor = cv2.KeyPoint(w / 2, h / 2, 2 * SIGMA, 0, 0, _ANCHOR_OCTAVE)
        kps_out, desc = self._sift.compute(st.gray, kps + [anchor])
        if desc is None or len(kps_out) != len(kps) + 1:  # OpenCV dropped some: recompute one by one
            desc = np.zeros((len(kps), 128), np.float32)
            for i, k in enumerate(kps):
                _, d = self._sift.compute(st.gray, [k, anchor])
                if d is not None and len(d) == 2:
                    desc[i] = d[0]
        return _root_sift(desc[: len(kps)])[inverse]


def _distinct(p: np.ndarray, size: np.ndarray, angle: np.ndarray, octave: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's descriptor of a keypoint depends on its position only through that position rounded
    in its octave's pixels (``calcSIFTDescriptor`` centres its window on ``cvRound(pt * scale)``):
    the first of each group of keypoints (OpenCV convention ``p``) that OpenCV describes alike, and
    each keypoint's group."""
    scale = unpack_octave(octave)[2]
    q = np.where(np.isfinite(p), p * scale[:, None], -1.0)  # float32 products (NaN points: one group)
    centre = np.rint(q).astype(np.int64)  # rounded half to even, as cvRound
    octave = np.asarray(octave, np.int64)
    size_bits = np.asarray(size, np.float32).view(np.uint32).astype(np.uint64)
    angle_bits = np.asarray(angle, np.float32).view(np.uint32).astype(np.uint64)
    # one int64 key per point where it fits (the few keypoint parameters of a call numbered first):
    # sorting it is ~10x faster than the rows of the 5-column key below
    _, kind = np.unique((size_bits << np.uint64(32)) | angle_bits, return_inverse=True)
    _, kind = np.unique((kind.reshape(-1).astype(np.int64) << 32) | (octave & 0xFFFFFFFF), return_inverse=True)
    kind = kind.reshape(-1)
    bound = 1 << 21
    fits = len(p) and octave.min() >= 0 and octave.max() < 1 << 32 and centre.min() >= -1 and centre.max() < bound - 1
    if fits and kind.max() < bound:
        key = ((centre[:, 0] + 1) << 42) | ((centre[:, 1] + 1) << 21) | kind
        _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
        return first, inverse.reshape(-1)
    key = np.stack([centre[:, 0], centre[:, 1], octave, size_bits.astype(np.int64), angle_bits.astype(np.int64)], 1)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return first, inverse.reshape(-1)


def _root_sift(desc: np.ndarray) -> np.ndarray:
    """RootSIFT: L1-normalise, square root, (L2-normalise against rounding)."""
    desc = np.asarray(desc, np.float32).reshape(-1, 128)
    desc = desc / np.maximum(desc.sum(axis=1, keepdims=True), 1e-8)
    desc = np.sqrt(desc)
    return desc / np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-8)
