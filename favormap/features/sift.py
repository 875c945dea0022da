"""OpenCV SIFT (128 channels, no weights). To sample descriptors at arbitrary positions the
extractor computes upright RootSIFT at a fixed support size everywhere (keypoints included), so
descriptors of keypoints and of patch pixels live in the same space."""

from __future__ import annotations

import cv2
import numpy as np

from .base import Extractor, Features, register


@register("sift")
class SIFTExtractor(Extractor):
    channels = 128

    def __init__(self, max_keypoints: int = 2048, device: str | None = None, size: float = 12.0):
        super().__init__(max_keypoints, device)
        self.size = float(size)
        self._sift = cv2.SIFT_create(nfeatures=self.max_keypoints, contrastThreshold=0.02)

    def extract(self, image: np.ndarray) -> Features:
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        kps = self._sift.detect(gray, None)
        kps = sorted(kps, key=lambda k: -k.response)[: self.max_keypoints]
        xy = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
        # several detections at one position (different orientations): keep one
        _, uniq = np.unique(np.round(xy, 1), axis=0, return_index=True)
        uniq.sort()
        xy = xy[uniq] + 0.5
        scores = np.array([kps[i].response for i in uniq], np.float32)
        feats = Features(xy, scores, None, (image.shape[1], image.shape[0]), gray)
        feats.descriptors = self.sample(feats, xy)
        return feats

    def sample(self, features: Features, points: np.ndarray) -> np.ndarray:
        gray = features.dense
        pts = np.asarray(points, np.float32).reshape(-1, 2) - 0.5
        if len(pts) == 0:
            return np.zeros((0, 128), np.float32)
        h, w = gray.shape
        pts[:, 0] = np.clip(pts[:, 0], 0, w - 1)
        pts[:, 1] = np.clip(pts[:, 1], 0, h - 1)
        kps = [cv2.KeyPoint(float(x), float(y), self.size, 0.0) for x, y in pts]
        kps_out, desc = self._sift.compute(gray, kps)
        if desc is None or len(kps_out) != len(kps):  # OpenCV dropped some: recompute one by one
            desc = np.zeros((len(kps), 128), np.float32)
            for i, k in enumerate(kps):
                _, d = self._sift.compute(gray, [k])
                if d is not None and len(d):
                    desc[i] = d[0]
        desc = desc.astype(np.float32)
        desc /= np.maximum(desc.sum(axis=1, keepdims=True), 1e-8)  # RootSIFT
        desc = np.sqrt(desc)
        desc /= np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-8)
        return desc
