"""The SIFT novel-view criterion of tests/test_voxels_view.py (rendered vs mean vs nearest training view, cosine to
the descriptor at the landmark's projection) on a plain map and on a map built with exact_poses.

    PYTHONPATH=. python docs/benchmarks/s38-prototypes/novel_view_exact.py plain|exact fast|balanced WORKDIR
"""

import sys, pathlib, functools
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[3] / "tests"))
import numpy as np
import favormap.build as fb
import test_voxels_view as t
from favormap.voxels import VoxelConfig

exact = sys.argv[1] == "exact"
quality = sys.argv[2]
orig = fb.BuildConfig
if exact:
    fb.BuildConfig = functools.partial(orig, exact_poses=True)
tmp = pathlib.Path(sys.argv[3]) / f"{sys.argv[1]}-{quality}"
tmp.mkdir(parents=True, exist_ok=True)
r = t._view_pairs(VoxelConfig.preset(quality), tmp, extractor="sift")
far = r["angle"] >= 10.0
for name, sel in (("far", far), ("near", ~far), ("all", np.ones_like(far))):
    print(name, sel.sum(), {k: round(float(r[k][sel].mean()), 4) for k in ("rendered", "nearest", "mean")})
print("gain over mean far %.4f all %.4f; vs nearest far %.4f all %.4f" % (
    r["rendered"][far].mean() - r["mean"][far].mean(), r["rendered"].mean() - r["mean"].mean(),
    r["rendered"][far].mean() - r["nearest"][far].mean(), r["rendered"].mean() - r["nearest"].mean()))
