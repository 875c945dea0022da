import numpy as np
from harness import run, d
from favormap.localize.refine import estimate_noise, refine_pose
def mk(loss=1.0, vf=None):
    def f(q):
        T, s, k = estimate_noise(q['pose0'], q['X'], q['kp'], q['K'], q['Xcov'], 0.5)
        v = None if vf is None else vf(q)
        return refine_pose(T, q['X'], q['kp'], q['K'], s * q['Xcov'], k, loss_scale=loss, variance_factor=v)
    return f
def show(name, f):
    r = run(f)
    ex = [r[k] for k in r if 'extrap' in k]; ho = [r[k] for k in r if 'holdout' in k]
    print(f"{name:28s} extrap {' '.join(f'{x:.2f}' for x in ex)}  (mean {np.mean(ex):.3f})  holdout {' '.join(f'{x:.2f}' for x in ho)}", flush=True)
show('default', mk())
for c in [0.5, 2.0, 4.0, 1e6]: show(f'loss {c}', mk(c))
for g in [0.5, 1.0]: show(f'size^{g}', mk(vf=lambda q, g=g: (q['size'] / np.median(q['size'])) ** (2 * g)))
show('guided x2', mk(vf=lambda q: np.where(q['by_desc'], 1.0, 2.0) if q['by_desc'] is not None else None))
show('guided x0.5', mk(vf=lambda q: np.where(q['by_desc'], 1.0, 0.5) if q['by_desc'] is not None else None))
