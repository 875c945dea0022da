"""Twenty-ninth session: `--align` with the final refinement's noise model fixed, and without the
guided step, as tools/bench_accuracy.py variants (run from the repository root):

    PYTHONPATH=. FAVORMAP_FOX=../shared/data/fox python docs/benchmarks/s29-prototypes/variants.py \
        --workdir /tmp/acc29f --reuse --splits fox-extrap,fox-holdout --priors noise --no-baseline \
        --variants "rendered,rendered align,rendered noise-fixed,rendered align noise-fixed,rendered no-guided,rendered align no-guided"
"""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "tools"))
import bench_accuracy as B
B.VARIANTS["rendered align noise-fixed"] = ("rendered", {"align": True, "refine_noise": "fixed"})
B.VARIANTS["rendered align no-guided"] = ("rendered", {"align": True, "guided_radius_px": 0})
sys.argv[0] = "bench_accuracy.py"
B.main()
