"""Paired comparison of two methods of one ``tools/bench_accuracy.py --json`` run (noise priors), by query name:
per seed the geometric mean of error(A) / error(B) over the queries both localized, then the log ratios
averaged over the seeds per query, with a 95 % bootstrap interval. ``{s}`` in a label is replaced by each
seed's suffix (``,-s1,-s2``: the seed-0 map has none, a build variant's seed-k map ``NAME-sK``); labels are
the run's method labels (``e2{s} rendered align``). s24-prototypes/paired.py does the same for one-word
method kinds only.

    SPLIT=fox-extrap python docs/benchmarks/s32-prototypes/paired_seeds.py RUN.json.gz "e2{s} rendered align" "e2 mean align" ",-s1,-s2"
"""

import gzip
import json
import os
import sys

import numpy as np

path, A, B = sys.argv[1], sys.argv[2], sys.argv[3]
seeds = sys.argv[4].split(",") if len(sys.argv) > 4 else [""]
SPLIT = os.environ.get("SPLIT", "fox-extrap")
raw = open(path, "rb").read()
rows = json.loads(gzip.decompress(raw) if path.endswith(".gz") else raw)
by = {(r["split"], r["method"]): r for r in rows if r["prior"] == "noise"}


def errors(label):
    r = by[(SPLIT, label)]
    return {q["name"]: (q["t_err"] if q["success"] else np.nan) for q in r["per_query"]}, r


logs = []
for s in seeds:
    a, ra = errors(A.format(s=s))
    b, rb = errors(B.format(s=s))
    keys = [k for k in a if k in b and np.isfinite(a[k]) and np.isfinite(b[k])]
    lr = np.log([a[k] / b[k] for k in keys])
    print(f"seed {s or '0'}: {np.exp(lr.mean()):.2f}  medians {ra['median_translation']:.5f} / {rb['median_translation']:.5f}  n={len(keys)}")
    logs.append(lr)
L = np.mean(logs, 0) if len({len(x) for x in logs}) == 1 else np.concatenate(logs)
rng = np.random.default_rng(0)
boot = [np.exp(rng.choice(L, len(L)).mean()) for _ in range(5000)]
print(f"pooled {np.exp(L.mean()):.2f} [{np.percentile(boot, 2.5):.2f}, {np.percentile(boot, 97.5):.2f}]")
