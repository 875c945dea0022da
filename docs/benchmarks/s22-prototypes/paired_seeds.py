"""Seed-pooled paired comparison of a build variant with the default (Adam) maps, from the json of
``tools/bench_accuracy.py --train-seeds 0,1,2 --build-variant NAME:...``: per split, each seed's
geometric mean of error / the default's error over the queries both localized, and the seed-pooled
figure (per query the log ratio averaged over the seeds; geometric mean, 95 % bootstrap interval).

    python docs/benchmarks/s22-prototypes/paired_seeds.py docs/benchmarks/accuracy-2026-11-28-s22-closed-l7seeds.json.gz l7r03
"""
import gzip
import json
import sys

import numpy as np

raw = open(sys.argv[1], "rb").read()  # a run's --json rows, plain or .gz (docs/benchmarks keeps them gzipped)
rows = json.loads(gzip.decompress(raw) if sys.argv[1].endswith(".gz") else raw)
variant, solver = sys.argv[2], (sys.argv[3] if len(sys.argv) > 3 else "lstsq")
by = {(r["split"], r["method"]): r for r in rows if r["prior"] == "noise"}
seeds = (("", ""), ("-s1", " s1"), ("-s2", " s2"))


def localized(r):
    return {q["name"]: q for q in r["per_query"] if q.get("success")}


for split in ("fox-holdout", "fox-extrap", "orbit"):
    per_seed = []
    for s, t in seeds:
        a, b = by.get((split, f"{solver} {variant}{s} rendered")), by.get((split, f"adam{t} rendered"))
        if not a or not b:
            continue
        A, B = localized(a), localized(b)
        lr = {k: np.log(A[k]["t_err"] / B[k]["t_err"]) for k in A if k in B}
        per_seed.append(lr)
        print(f"{split:12s} seed{s or '-s0'}: {np.exp(np.mean(list(lr.values()))):.2f}  median {a['median_translation']:.5f} "
              f"(default {b['median_translation']:.5f}), p90 {a['p90_translation']:.4f} ({b['p90_translation']:.4f})")
    if not per_seed:  # split not in this run
        continue
    keys = set.intersection(*(set(d) for d in per_seed))
    v = np.array([np.mean([d[k] for d in per_seed]) for k in keys])
    rng = np.random.default_rng(0)
    bs = [np.exp(rng.choice(v, len(v)).mean()) for _ in range(4000)]
    print(f"{split:12s} pooled {np.exp(v.mean()):.2f} [{np.percentile(bs, 2.5):.2f}, {np.percentile(bs, 97.5):.2f}] ({len(v)} queries)")
