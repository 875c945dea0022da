"""Twenty-eighth session: tools/bench_accuracy.py with the prototype extractors of siftcat.py
registered (same arguments as the tool). Run from the repository root:

    PYTHONPATH=. FAVORMAP_FOX=../shared/data/fox python docs/benchmarks/s28-prototypes/variants.py \
        --workdir /tmp/acc28 --splits fox-extrap --priors noise --no-baseline \
        --variants rendered,mean,nearest-view --extractor sift,siftcat"""

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[2] / "tools"))
sys.path.insert(0, str(HERE))
import bench_accuracy as B  # noqa: E402
import siftcat  # noqa: E402,F401 - registers the prototype extractors

if __name__ == "__main__":
    sys.argv[0] = "bench_accuracy.py"
    B.main()
