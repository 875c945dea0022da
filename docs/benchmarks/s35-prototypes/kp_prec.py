"""Thirty-fifth session: keypoint precision on the synthetic room (640 x 480, orbit frames 2/4, 8/10,
14/16): mutual nearest-neighbour matches, each first-view keypoint carried to the second view through the
rendered depth and the exact poses; share within 3 px and the median distance of those. ALIKED with three
sub-pixel refinements (its soft-argmax, none, a parabola), then favormap's SIFT and DISK.
Run: PYTHONPATH=. python docs/benchmarks/s35-prototypes/kp_prec.py"""
import numpy as np, torch, torch.nn.functional as F, time
from favormap import features
from favormap.features.heatmap import subpixel_offsets
from favormap.synthetic import camera_path, make_camera, make_room, render, backproject, project
torch.set_num_threads(2)
room, cam = make_room(0), make_camera(640, 480)
path = camera_path(24)
ex = features.create("aliked", max_keypoints=2048, score_threshold=0.0)
def run(mode, i, j):
    out = []
    for k in (i, j):
        img, depth = render(room, cam, path[k])
        x = torch.from_numpy(img.copy()).permute(2, 0, 1)[None].float() / 255
        with torch.inference_mode():
            fmap, score = ex.model.dense(x)
            s = score[0, 0]
            xy, sc = ex._detect(s)  # soft-argmax
            if mode == "int":
                xy = xy.round()
            elif mode == "parab":
                xy = xy.round(); xy = xy + subpixel_offsets(s, xy.long())
            d = ex.model.desc_head(fmap[0].permute(1, 2, 0).contiguous(), xy)
        out.append((xy.numpy() + 0.5, d.numpy(), depth))
    (ka, da, dep), (kb, db, _) = out
    S = da @ db.T; a = S.argmax(1); m = np.flatnonzero(S.argmax(0)[a] == np.arange(len(a)))
    r, c = (ka[m, 1] - 0.5).astype(int), (ka[m, 0] - 0.5).astype(int)
    X = backproject(cam, path[i], ka[m], dep[r, c])
    uv, _ = project(cam, path[j], X)
    e = np.linalg.norm(uv - kb[a[m]], axis=1)
    good = e < 3
    return len(ka), len(m), good.mean(), np.median(e[good])
for mode in ("soft", "int", "parab"):
    res = [run(mode, i, i + 2) for i in (2, 8, 14)]
    print(mode, "kp %d matches %d correct %.2f median err of correct %.3f px" % tuple(np.mean(res, 0)))
sift = features.create("sift", max_keypoints=2048)
dsk = features.create("disk", max_keypoints=2048)
for name, e_ in (("sift", sift), ("disk", dsk)):
    res = []
    for i in (2, 8, 14):
        fs = []
        for k in (i, i + 2):
            img, depth = render(room, cam, path[k]); f = e_.extract(img); fs.append((f.keypoints, f.descriptors, depth))
        (ka, da, dep), (kb, db, _) = fs
        S = da @ db.T; a = S.argmax(1); m = np.flatnonzero(S.argmax(0)[a] == np.arange(len(a)))
        r, c = (ka[m, 1] - 0.5).astype(int), (ka[m, 0] - 0.5).astype(int)
        X = backproject(cam, path[i], ka[m], dep[r, c]); uv, _ = project(cam, path[i + 2], X)
        e = np.linalg.norm(uv - kb[a[m]], axis=1); good = e < 3
        res.append((len(ka), len(m), good.mean(), np.median(e[good])))
    print(name, "kp %d matches %d correct %.2f median err of correct %.3f px" % tuple(np.mean(res, 0)))
