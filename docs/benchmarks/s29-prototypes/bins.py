"""Per angle bin, the geometric mean of one method's error over another's on the orbit's queries
(noise priors), e.g. issue 11 (c) on aligned keypoints. Bins: [0, 10), [10, 20), [20, 40), [40, 180)
degrees to the nearest mapping view (the query at exactly 40 degrees falls in the last).

    python docs/benchmarks/s29-prototypes/bins.py docs/benchmarks/accuracy-2026-11-28-s29-pl9.json.gz \
        "pl9 rendered align" "pl9 mean align" "pl9 nearest-view align"
"""

import gzip
import json
import sys

import numpy as np

rows = json.loads(gzip.decompress(open(sys.argv[1], "rb").read()))
by = {(r["split"], r["method"]): r for r in rows if r["prior"] == "noise"}


def errors(label):
    return {q["name"]: (q["t_err"], q["angle_deg"]) for q in by[("orbit", label)]["per_query"]}


ref = errors(sys.argv[2])
for other in sys.argv[3:]:
    o = errors(other)
    out = []
    for lo, hi in ((0, 10), (10, 20), (20, 40), (40, 180)):
        ks = [k for k in ref if lo <= ref[k][1] < hi]
        out.append(f"{np.exp(np.mean([np.log(o[k][0] / ref[k][0]) for k in ks])):.2f} ({len(ks)})")
    print(f"{other} / {sys.argv[2]}, 0-10 / 10-20 / 20-40 / > 40 deg:", " / ".join(out))
