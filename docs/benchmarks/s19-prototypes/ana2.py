import pickle, numpy as np
from favormap.geometry import project, camera_centers
from favormap.localize.refine import _image_covariances, _projection_jacobians
from favormap.mapfile import Map
m = Map.open('/tmp/acc15/fox-extrap.h5')
d = pickle.load(open('/tmp/s19/cap.pkl','rb'))['fox-extrap']
F = {k: [] for k in ['r', 'rpar', 'lstd', 'tl', 'va', 'rep', 'depth', 'qang', 'size']}
for r in d:
    gt = r['gt']; X = r['X']; rows = r['rows']
    res = project(r['K'], gt, X) - r['kp']
    P = X @ gt[:3,:3].T + gt[:3,3]
    V = _image_covariances(_projection_jacobians(P, r['K']), gt[:3,:3], r['Xcov'], np.zeros((2,2)))
    c = np.linalg.inv(gt)[:3, 3]
    ray = X - c; ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    vd = m.view_dir[rows]
    F['rpar'].append(np.zeros(len(X)))
    F['r'].append(np.linalg.norm(res, axis=1)); F['lstd'].append(np.sqrt(np.trace(V, axis1=1, axis2=2)))
    F['tl'].append(m.track_length[rows]); F['va'].append(m.view_angle[rows]); F['rep'].append(m.reproj_error[rows])
    F['depth'].append(P[:, 2]); F['size'].append(r['size'])
    F['qang'].append(np.degrees(np.arccos(np.clip(np.abs((ray * vd).sum(1)), -1, 1))))
F = {k: np.concatenate(v) for k, v in F.items()}
lr = np.log(np.maximum(F['r'], 1e-3))
print('n', len(lr))
for k in ['lstd', 'tl', 'va', 'rep', 'depth', 'qang', 'size']:
    x = F[k].astype(float)
    q = np.quantile(x, [0, .2, .4, .6, .8, 1])
    b = np.clip(np.searchsorted(q, x, side='right') - 1, 0, 4)
    meds = [np.median(F['r'][b == i]) for i in range(5)]
    rho = np.corrcoef(np.argsort(np.argsort(x)), np.argsort(np.argsort(F['r'])))[0, 1]
    print(f"{k:6s} spearman {rho:+.3f}  quintile medians |r| {np.round(meds, 3)}  edges {np.round(q, 3)}")
