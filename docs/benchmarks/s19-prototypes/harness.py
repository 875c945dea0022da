import pickle, numpy as np, sys
from favormap.localize.refine import estimate_noise, refine_pose
d = pickle.load(open('/tmp/s19/cap.pkl', 'rb'))
def centre(T): return -T[:3, :3].T @ T[:3, 3]
def default(q):
    T, s, k = estimate_noise(q['pose0'], q['X'], q['kp'], q['K'], q['Xcov'], 0.5)
    return refine_pose(T, q['X'], q['kp'], q['K'], s * q['Xcov'], k, loss_scale=1.0)
def run(fn, keys=None):
    out = {}
    for key, qs in d.items():
        if keys and key not in keys: continue
        e = [np.linalg.norm(centre(fn(q)) - centre(q['gt'])) for q in qs]
        out[key] = np.median(e) * 1000
    return out
if __name__ == '__main__':
    r = run(default); print({k: round(v, 2) for k, v in r.items()})
    r = run(lambda q: q['est']); print('est', {k: round(v, 2) for k, v in r.items()})
