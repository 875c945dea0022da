"""Descriptor-level novel-view figures of SIFT grids (tests/test_voxels_view.py's scene) for voxel presets
with overrides: python docs/benchmarks/s33-prototypes/vp.py balanced "balanced:prior_mean_deg=30" ..."""
import sys, pathlib, tempfile, numpy as np
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[3] / "tests"))
import test_voxels_view as t
from favormap.voxels import VoxelConfig
for spec in sys.argv[1:]:
    q, *kv = spec.split(":")
    over = {}
    for a in kv:
        k, v = a.split("=")
        over[k] = float(v) if v.replace('.', '').replace('-', '').replace('e', '').isdigit() else v
    r = t._view_pairs(VoxelConfig.preset(q, **over), pathlib.Path(tempfile.mkdtemp()), extractor="sift")
    far = r["angle"] >= 10
    print(spec, f"vs mean far {r['rendered'][far].mean()-r['mean'][far].mean():+.4f} all {r['rendered'].mean()-r['mean'].mean():+.4f} vs nearest far {r['rendered'][far].mean()-r['nearest'][far].mean():+.4f}", flush=True)
