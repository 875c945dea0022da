"""Per angle bin, the geometric mean of one method's error over another's, query by query (noise
priors), pooled over training seeds (the log ratio averaged over the seeds per query), with a 95 %
bootstrap interval over the queries: e.g. issue 11 (c) on aligned keypoints. Bins: [0, 10), [10, 20),
[20, 40), [40, 180) degrees to the nearest mapping view (a query at exactly 40 degrees falls in the last).

    python docs/benchmarks/s29-prototypes/bins.py docs/benchmarks/accuracy-2026-11-28-s29-pl9.json.gz \
        "pl9 rendered align" "pl9 mean align" "pl9 nearest-view align"
    python docs/benchmarks/s29-prototypes/bins.py --split orbit-dense --seeds 0,1,2 \
        docs/benchmarks/accuracy-2026-11-28-s29-orbit-dense-align.json.gz "rendered align" "mean align"
"""

import argparse
import gzip
import json

import numpy as np

ap = argparse.ArgumentParser()
ap.add_argument("json")
ap.add_argument("reference")
ap.add_argument("others", nargs="+")
ap.add_argument("--split", default="orbit")
ap.add_argument("--seeds", default="0")
args = ap.parse_args()
rows = json.loads(gzip.decompress(open(args.json, "rb").read()))
by = {(r["split"], r["method"]): r for r in rows if r["prior"] == "noise"}
seeds = [int(s) for s in args.seeds.split(",")]


def seeded(label, s):
    """The label of seed s: 'rendered align' -> 's1 rendered align' (the default map),
    'pl9 rendered align' -> 'pl9-s1 rendered align' (a build variant)."""
    if not s or (args.split, f"s{s} {label}") in by:
        return f"s{s} {label}" if s else label
    head, _, rest = label.partition(" ")
    return f"{head}-s{s} {rest}"


def errors(label, s):
    return {q["name"]: (q["t_err"], q["angle_deg"]) for q in by[(args.split, seeded(label, s))]["per_query"]}


rng = np.random.default_rng(0)
for other in args.others:
    logs, angle = {}, {}
    for s in seeds:
        ref, o = errors(args.reference, s), errors(other, s)
        for k in ref:
            logs.setdefault(k, []).append(np.log(o[k][0] / ref[k][0]))
            angle[k] = ref[k][1]
    out = []
    for lo, hi in ((0, 10), (10, 20), (20, 40), (40, 180)):
        v = np.array([np.mean(logs[k]) for k in logs if lo <= angle[k] < hi])
        boot = [np.mean(rng.choice(v, len(v))) for _ in range(2000)]
        lo_ci, hi_ci = np.exp(np.percentile(boot, [2.5, 97.5]))
        out.append(f"{np.exp(v.mean()):.2f} [{lo_ci:.2f}, {hi_ci:.2f}] ({len(v)})")
    print(f"{other} / {args.reference}, seeds {args.seeds}, 0-10 / 10-20 / 20-40 / > 40 deg:", " / ".join(out))
