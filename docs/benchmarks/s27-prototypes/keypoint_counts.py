"""OpenCV SIFT keypoints per frame at favormap's contrast threshold, uncapped. Usage: PYTHONPATH=. python
keypoint_counts.py SEQ."""

import sys

import numpy as np

from favormap.build import BuildConfig, ExtractorSpec, extract_sequence
from favormap.io import read_sequence

seq = read_sequence(sys.argv[1])
cfg = BuildConfig()
ff = extract_sequence(seq, ExtractorSpec(cfg.extractor, 100000), cfg.max_side)
print(
    "favormap kp per frame (uncapped)",
    [len(f.keypoints) for f in ff.features][:10],
    np.mean([len(f.keypoints) for f in ff.features]),
)
