import sys, numpy as np
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[3] / "tools"))
import bench_accuracy as B
rows = B.read_rows(sys.argv[1])
by = {r["method"]: r for r in rows}
def errs(m): return np.array([q["t_err"] if q.get("success") else np.inf for q in by[m]["per_query"]], float)
for a, b in [x.split("|") for x in sys.argv[2:]]:
    print(f"{a} / {b}: {B._ratio_cell(B.paired_ratio(errs(a), errs(b)))}")
