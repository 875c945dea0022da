import time, pickle, numpy as np, torch
from concurrent.futures import ThreadPoolExecutor
torch.set_num_threads(2)
ff = pickle.load(open("/tmp/s26/ff.pkl", "rb"))
D = [torch.from_numpy(np.ascontiguousarray(f.descriptors)) for f in ff.features]
pairs = [(a, b) for a in range(40) for b in range(a + 1, min(40, a + 11))]
def full(a, b):
    s = (D[a] @ D[b].T).numpy()
    ab = s.argmax(1); return ab, s.max(0)
def gemm_only(a, b):
    return D[a] @ D[b].T
def blocked(a, b, B=256):
    da, dbt = D[a], D[b].T.contiguous()
    n = len(da); ab = np.empty(n, np.int64); cm = None
    for i in range(0, n, B):
        s = (da[i:i+B] @ dbt).numpy()
        ab[i:i+B] = s.argmax(1)
        m = s.max(0); cm = m if cm is None else np.maximum(cm, m, out=cm)
    return ab, cm
for name, fn in [("gemm", gemm_only), ("full", full), ("blocked256", blocked), ("blocked128", lambda a, b: blocked(a, b, 128)), ("blocked512", lambda a, b: blocked(a, b, 512))]:
    t = time.perf_counter()
    for a, b in pairs: fn(a, b)
    print(name, round(time.perf_counter() - t, 3))
# threaded, torch 1 thread each
torch.set_num_threads(1)
for name, fn in [("thr-full", full), ("thr-blocked256", blocked)]:
    t = time.perf_counter()
    with ThreadPoolExecutor(2) as ex: list(ex.map(lambda p: fn(*p), pairs))
    print(name, round(time.perf_counter() - t, 3))
torch.set_num_threads(2)
ref = [full(a, b) for a, b in pairs]
torch.set_num_threads(1)
with ThreadPoolExecutor(2) as ex: thr = list(ex.map(lambda p: blocked(*p), pairs))
with ThreadPoolExecutor(2) as ex: thr2 = list(ex.map(lambda p: full(*p), pairs))
print("blocked equal", all(np.array_equal(x[0], y[0]) and np.array_equal(x[1], y[1]) for x, y in zip(ref, thr)))
print("full equal", all(np.array_equal(x[0], y[0]) and np.array_equal(x[1], y[1]) for x, y in zip(ref, thr2)))
