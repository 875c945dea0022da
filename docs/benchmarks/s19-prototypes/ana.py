import pickle, numpy as np
from favormap.geometry import project
from favormap.localize.refine import _image_covariances, _projection_jacobians
d = pickle.load(open('/tmp/s19/cap.pkl','rb'))
for key in ['fox-extrap', 'fox-holdout']:
    rs, ss, ls, oc = [], [], [], []
    for r in d[key]:
        gt = r['gt']; X = r['X']
        res = project(r['K'], gt, X) - r['kp']
        P = X @ gt[:3,:3].T + gt[:3,3]
        V = _image_covariances(_projection_jacobians(P, r['K']), gt[:3,:3], r['Xcov'], np.zeros((2,2)))
        rs.append(np.linalg.norm(res, axis=1)); ss.append(r['size']); ls.append(np.sqrt(np.trace(V, axis1=1, axis2=2))); oc.append(r['octave'] & 255)
    rs, ss, ls, oc = map(np.concatenate, (rs, ss, ls, oc))
    oc = np.where(oc > 127, oc - 256, oc)
    print(key, len(rs), 'size pct', np.percentile(ss, [10, 50, 90]).round(2))
    for o in np.unique(oc):
        m = oc == o
        print(f'  octave {o:2d} n={m.sum():5d} size {np.median(ss[m]):5.2f} |r| med {np.median(rs[m]):.3f} rms {np.sqrt(np.mean(np.minimum(rs[m],10)**2)):.3f}  landmark std {np.median(ls[m]):.3f}')
