import time, pickle, numpy as np, torch, sys
from concurrent.futures import ThreadPoolExecutor
ff = pickle.load(open("/tmp/s26/ff.pkl", "rb"))
D = [np.ascontiguousarray(f.descriptors) for f in ff.features]
DT = [torch.from_numpy(d) for d in D]
pairs = [(a, b) for a in range(40) for b in range(a + 1, min(40, a + 11))]
def np_full(a, b):
    s = D[a] @ D[b].T
    return s.argmax(1), s.max(0)
def t_full(a, b):
    s = (DT[a] @ DT[b].T).numpy()
    return s.argmax(1), s.max(0)
torch.set_num_threads(1)
for name, fn in [("torch-thr", t_full), ("numpy-thr", np_full)]:
    for _ in range(2):
        t = time.perf_counter()
        with ThreadPoolExecutor(2) as ex: r = list(ex.map(lambda p: fn(*p), pairs))
        print(name, round(time.perf_counter() - t, 3))
t = time.perf_counter(); r2 = [np_full(*p) for p in pairs]; print("numpy serial (openblas own threads)", round(time.perf_counter() - t, 3))
rt = [t_full(*p) for p in pairs]
same = sum(np.array_equal(x[0], y[0]) for x, y in zip(r2, rt)); print("argmax identical pairs", same, "of", len(pairs))
diff = sum(int((x[0] != y[0]).sum()) for x, y in zip(r2, rt)); print("rows differing", diff)
