"""Prototype extractors (twenty-eighth session, not in the package): SIFT keypoints, each described by
its RootSIFT descriptor *and* the DISK descriptor field sampled at it, concatenated
(unit(sift) ; w * unit(disk)) / sqrt(1 + w^2): a cosine of two such descriptors is the weighted
mean (c_sift + w^2 c_disk) / (1 + w^2) of the halves' cosines.

SIFT's half keeps what makes SIFT maps precise (its keypoints and their scale-invariant matches);
DISK's half carries the view dependence that rendering captures and a track's mean does not
(twenty-first session: on DISK maps rendered 1.8-2.3x better than the mean on fox extrapolation).

Tracks are built with SIFT's own descriptors (the build's extraction, max_keypoints 2048: the
landmarks are those of the SIFT map of the same tracking); the training patches (``sample``) and the
query's keypoints (max_keypoints 4096) get the concatenation. Registered as ``siftcat`` (w = 1),
``siftcat05`` (w = 0.5), ``siftcat2`` (w = 2)."""

import numpy as np

from favormap.features.base import Extractor, Features, register
from favormap.features.disk import DISKExtractor
from favormap.features.sift import SIFTExtractor


class _State:
    def __init__(self, sift, disk):
        self.sift, self.disk = sift, disk


class SiftCat(Extractor):
    channels = 256
    match_ratio = 0.9  # SIFT's, for the prior-free step
    weight = 1.0

    def __init__(self, max_keypoints=2048, device=None, orientations="strongest", contrast_threshold=0.02):
        super().__init__(max_keypoints, device)
        self.orientations = orientations
        self.sift = SIFTExtractor(max_keypoints, device, orientations=orientations, contrast_threshold=contrast_threshold)
        self.disk = DISKExtractor(16, device)

    @property
    def match_threshold(self):  # the halves' thresholds (SIFT 0.7, DISK 0.5) weighted alike
        w2 = self.weight**2
        return (0.7 + w2 * 0.5) / (1 + w2)

    def config(self):
        return {**super().config(), "keypoints": "sift", "descriptors": f"rootsift+{self.weight:g}*disk-depth"}

    def _cat(self, s, d):
        w = self.weight
        return (np.concatenate([s, w * d], axis=1) / np.sqrt(1 + w * w)).astype(np.float32)

    def extract(self, image):
        fs = self.sift.extract(image)
        fd = self.disk.extract(image)
        st = _State(fs, fd)
        if self.max_keypoints == 2048:  # the build's tracking: SIFT's own descriptors
            desc = fs.descriptors
        else:
            desc = self._cat(fs.descriptors, self.disk.sample(fd, fs.keypoints))
        return Features(fs.keypoints, fs.scores, desc, fs.image_size, st)

    def sample(self, features, points):
        st = features.dense
        return self._cat(self.sift.sample(st.sift, points), self.disk.sample(st.disk, points))


@register("siftcat")
class SiftCat1(SiftCat):
    weight = 1.0


@register("siftcat05")
class SiftCat05(SiftCat):
    weight = 0.5


@register("siftcat2")
class SiftCat2(SiftCat):
    weight = 2.0
