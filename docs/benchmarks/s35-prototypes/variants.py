"""Thirty-fifth session: tools/bench_accuracy.py with prototype ALIKED settings registered as extractors
(same arguments as the tool). Run from the repository root:

    PYTHONPATH=. FAVORMAP_FOX=../shared/data/fox python docs/benchmarks/s35-prototypes/variants.py \
        --workdir W --splits fox-extrap --priors noise --no-baseline --extractor aliked-t0,aliked-t0p \
        --variants "rendered,mean,nearest-view,rendered align,mean align"
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "tools"))
import bench_accuracy as B  # noqa: E402
from favormap.features.base import register
from favormap.features.aliked import ALIKEDExtractor


@register("aliked-t0")
class T0(ALIKEDExtractor):
    def __init__(self, max_keypoints=2048, device=None):
        super().__init__(max_keypoints, device, score_threshold=0.0)


@register("aliked-t0p")
class T0P(ALIKEDExtractor):
    def __init__(self, max_keypoints=2048, device=None):
        super().__init__(max_keypoints, device, score_threshold=0.0, subpixel="parabola")


if __name__ == "__main__":
    sys.argv[0] = "bench_accuracy.py"
    B.main()
