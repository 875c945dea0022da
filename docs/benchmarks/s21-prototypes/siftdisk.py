"""Prototype extractor: SIFT keypoints (geometry), DISK descriptors sampled at them (appearance)."""
import numpy as np
from favormap.features.base import Extractor, Features, register
from favormap.features.sift import SIFTExtractor
from favormap.features.disk import DISKExtractor


@register("siftdisk")
class SiftDisk(Extractor):
    channels = 128
    match_ratio = 1.0

    def __init__(self, max_keypoints=2048, device=None, **sift_kw):
        super().__init__(max_keypoints, device)
        sift_kw.pop("orientations", None)
        self.sift = SIFTExtractor(max_keypoints, device, orientations="strongest", **sift_kw)
        self.disk = DISKExtractor(16, device)

    def config(self):
        return {**super().config(), "keypoints": "sift", "descriptors": "disk-depth"}

    def extract(self, image):
        fs = self.sift.extract(image)
        fd = self.disk.extract(image)
        desc = self.disk.sample(fd, fs.keypoints)
        return Features(fs.keypoints, fs.scores, desc, fs.image_size, fd.dense)

    def sample(self, features, points):
        return self.disk.sample(Features(None, None, None, features.image_size, features.dense), points)


@register("siftdisk2")
class SiftDisk2(SiftDisk):
    """Tracks with SIFT's descriptors (the build's extraction: max_keypoints 2048), DISK descriptors
    everywhere else (patches via sample(); the localizer's extraction: max_keypoints 4096)."""

    def extract(self, image):
        fs = self.sift.extract(image)
        fd = self.disk.extract(image)
        desc = fs.descriptors if self.max_keypoints == 2048 else self.disk.sample(fd, fs.keypoints)
        return Features(fs.keypoints, fs.scores, desc, fs.image_size, fd.dense)
