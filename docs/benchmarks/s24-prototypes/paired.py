"""Seed-pooled paired comparison of two maps of one ``tools/bench_accuracy.py --train-seeds 0,1,2`` run
(noise priors): per split and seed, the geometric mean of error(A) / error(B) over the queries both
localized; pooled over the seeds per query (log ratio averaged), with a 95 % bootstrap interval.
A and B are method labels without the seed suffix: ``pi rendered`` (build variant ``pi``), ``rendered``
(the default map), ``pi mean`` ...

    python docs/benchmarks/s24-prototypes/paired.py RUN.json "pi rendered" "rendered"
"""

import gzip
import json
import sys

import numpy as np

raw = open(sys.argv[1], "rb").read()  # a run's --json rows, plain or .gz (docs/benchmarks keeps them gzipped)
rows = json.loads(gzip.decompress(raw) if sys.argv[1].endswith(".gz") else raw)
A_label, B_label = sys.argv[2], sys.argv[3]
PRIOR = sys.argv[4] if len(sys.argv) > 4 else "noise"
by = {(r["split"], r["method"]): r for r in rows if r["prior"] == PRIOR}


def seeded(label, s):
    """The label of seed s: 'rendered' -> 's1 rendered', 'pi rendered' -> 'pi-s1 rendered'."""
    if not s:
        return label
    head, _, kind = label.rpartition(" ")
    return f"{head}-s{s} {kind}" if head else f"s{s} {kind}"


def localized(r):
    return {q["name"]: q for q in r["per_query"] if q.get("success")}


for split in ("fox-holdout", "fox-extrap", "orbit"):
    per_seed = []
    for s in (0, 1, 2):
        a, b = by.get((split, seeded(A_label, s))), by.get((split, seeded(B_label, s)))
        if not a or not b:
            continue
        A, B = localized(a), localized(b)
        lr = {k: np.log(A[k]["t_err"] / B[k]["t_err"]) for k in A if k in B}
        per_seed.append(lr)
        print(
            f"{split:12s} seed {s}: {np.exp(np.mean(list(lr.values()))):.2f}  median {a['median_translation']:.5f} "
            f"({b['median_translation']:.5f}), p90 {a['p90_translation']:.4f} ({b['p90_translation']:.4f}), "
            f"localized {len(A)} / {len(B)}"
        )
    if not per_seed:
        continue
    keys = set.intersection(*(set(d) for d in per_seed))
    v = np.array([np.mean([d[k] for d in per_seed]) for k in keys])
    rng = np.random.default_rng(0)
    bs = [np.exp(rng.choice(v, len(v)).mean()) for _ in range(4000)]
    print(
        f"{split:12s} pooled {np.exp(v.mean()):.2f} [{np.percentile(bs, 2.5):.2f}, {np.percentile(bs, 97.5):.2f}] "
        f"({len(v)} queries)"
    )
