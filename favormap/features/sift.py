"""OpenCV SIFT (128 channels, no weights), RootSIFT-normalised.

Keypoints are described with their own scale and orientation, as in any SIFT pipeline (the
structure baseline, COLMAP). To sample descriptors at arbitrary positions (the S x S training
patches around a landmark's observation), a point takes the scale and orientation of the nearest
detected keypoint within ``support_px`` pixels (so a patch around a keypoint is described in that
keypoint's frame and matches it), and a fixed upright ``size`` elsewhere."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from .base import Extractor, Features, register


@dataclass
class _SiftState:
    gray: np.ndarray
    xy: np.ndarray  # (N, 2) keypoints, COLMAP convention
    size: np.ndarray  # (N,) OpenCV keypoint size
    angle: np.ndarray  # (N,) OpenCV keypoint angle (deg)


@register("sift")
class SIFTExtractor(Extractor):
    channels = 128
    match_ratio = 0.8  # Lowe's test when matching against a whole map (the localizer's prior-free step)

    def __init__(
        self, max_keypoints: int = 2048, device: str | None = None, size: float = 12.0, support_px: float = 4.0
    ):
        super().__init__(max_keypoints, device)
        self.size = float(size)
        self.support_px = float(support_px)
        self._sift = cv2.SIFT_create(nfeatures=self.max_keypoints, contrastThreshold=0.02)

    def extract(self, image: np.ndarray) -> Features:
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        kps = self._sift.detect(gray, None)
        kps = sorted(kps, key=lambda k: -k.response)[: self.max_keypoints]
        xy = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
        # several detections at one position (different orientations): keep the strongest
        _, uniq = np.unique(np.round(xy, 1), axis=0, return_index=True)
        uniq.sort()
        state = _SiftState(
            gray,
            xy[uniq] + 0.5,
            np.array([kps[i].size for i in uniq], np.float32),
            np.array([kps[i].angle for i in uniq], np.float32),
        )
        scores = np.array([kps[i].response for i in uniq], np.float32)
        feats = Features(state.xy, scores, None, (image.shape[1], image.shape[0]), state)
        feats.descriptors = self._describe(state, state.xy, state.size, state.angle)
        return feats

    def sample(self, features: Features, points: np.ndarray) -> np.ndarray:
        st: _SiftState = features.dense
        pts = np.asarray(points, np.float32).reshape(-1, 2)
        size = np.full(len(pts), self.size, np.float32)
        angle = np.zeros(len(pts), np.float32)
        if len(pts) and len(st.xy):
            d = torch.cdist(torch.as_tensor(pts), torch.as_tensor(st.xy))
            dist, nn = d.min(1)
            near = (dist <= self.support_px).numpy()
            nn = nn.numpy()
            size[near], angle[near] = st.size[nn[near]], st.angle[nn[near]]
        return self._describe(st, pts, size, angle)

    def _describe(self, st: _SiftState, pts: np.ndarray, size: np.ndarray, angle: np.ndarray) -> np.ndarray:
        if len(pts) == 0:
            return np.zeros((0, 128), np.float32)
        h, w = st.gray.shape
        p = np.asarray(pts, np.float32) - 0.5
        p[:, 0] = np.clip(p[:, 0], 0, w - 1)
        p[:, 1] = np.clip(p[:, 1], 0, h - 1)
        kps = [cv2.KeyPoint(float(x), float(y), float(s), float(a)) for (x, y), s, a in zip(p, size, angle)]
        kps_out, desc = self._sift.compute(st.gray, kps)
        if desc is None or len(kps_out) != len(kps):  # OpenCV dropped some: recompute one by one
            desc = np.zeros((len(kps), 128), np.float32)
            for i, k in enumerate(kps):
                _, d = self._sift.compute(st.gray, [k])
                if d is not None and len(d):
                    desc[i] = d[0]
        desc = desc.astype(np.float32)
        desc /= np.maximum(desc.sum(axis=1, keepdims=True), 1e-8)  # RootSIFT
        desc = np.sqrt(desc)
        desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-8)
        return desc
