"""Thirty-fifth session: ALIKED (favormap's network, the published detection: threshold 0.2, soft-argmax)
against OpenCV SIFT on two pairs of fox frames at 640 px: mutual nearest neighbours and the share of them
that are inliers of a fundamental matrix at 1 px (RANSAC). Run: python docs/benchmarks/s35-prototypes/match_test.py"""
import sys, time, numpy as np, cv2, torch, torch.nn.functional as F
torch.set_num_threads(2)
from favormap.features.aliked import ALIKEDExtractor
net = ALIKEDExtractor(max_keypoints=2048).model

def detect(score, k=2048, radius=2, th=0.2):
    s = score[0, 0]
    h, w = s.shape
    ks = 2 * radius + 1
    mx = F.max_pool2d(s[None, None], ks, 1, radius)[0, 0]
    m = (s == mx) & (s > th)
    m[:radius] = m[-radius:] = False; m[:, :radius] = m[:, -radius:] = False
    yx = m.nonzero()
    sc = s[yx[:, 0], yx[:, 1]]
    top = torch.argsort(-sc)[:k]
    yx, sc = yx[top], sc[top]
    # soft-argmax in a 5x5 window, temperature 0.1
    pad = F.pad(s[None, None], (radius,) * 4)[0, 0]
    r = torch.arange(ks)
    win = pad[yx[:, 0, None, None] + r.view(1, ks, 1), yx[:, 1, None, None] + r.view(1, 1, ks)].reshape(len(yx), -1)
    e = ((win - win.max(1, keepdim=True).values) / 0.1).exp()
    gy, gx = torch.meshgrid(r - radius, r - radius, indexing="ij")
    dx = (e * gx.reshape(1, -1)).sum(1) / e.sum(1)
    dy = (e * gy.reshape(1, -1)).sum(1) / e.sum(1)
    return torch.stack([yx[:, 1] + dx, yx[:, 0] + dy], 1).float(), sc

def run(path, scale=640):
    img = cv2.imread(path)[:, :, ::-1]
    h, w = img.shape[:2]; f = scale / max(h, w)
    img = cv2.resize(img, (round(w * f), round(h * f)), interpolation=cv2.INTER_AREA)
    x = torch.from_numpy(img.copy()).permute(2, 0, 1)[None].float() / 255
    t = time.time()
    with torch.inference_mode():
        fmap, score = net.dense(x)
        kp, sc = detect(score)
        d = net.desc_head(fmap[0].permute(1, 2, 0).contiguous(), kp)
    return kp.numpy(), d.numpy(), time.time() - t, img

def mutual(d1, d2):
    s = d1 @ d2.T
    a, b = s.argmax(1), s.argmax(0)
    i = np.flatnonzero(b[a] == np.arange(len(a)))
    return i, a[i], s[i, a[i]]

for pair in [(1, 3), (1, 8)]:
    p = [f"/work/shared/data/fox/images/{i:04d}.jpg" for i in pair]
    k1, d1, t1, _ = run(p[0]); k2, d2, t2, _ = run(p[1])
    i, j, s = mutual(d1, d2)
    F_, inl = cv2.findFundamentalMat(k1[i], k2[j], cv2.FM_RANSAC, 1.0, 0.999)
    # SIFT for comparison
    sift = cv2.SIFT_create(2048)
    g = [cv2.cvtColor(cv2.resize(cv2.imread(q), None, fx=640/1920, fy=640/1920, interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2GRAY) for q in p]
    ka, da = sift.detectAndCompute(g[0], None); kb, db = sift.detectAndCompute(g[1], None)
    da /= np.linalg.norm(da, axis=1, keepdims=True); db /= np.linalg.norm(db, axis=1, keepdims=True)
    ii, jj, _ = mutual(da, db)
    pa = np.float32([ka[q].pt for q in ii]); pb = np.float32([kb[q].pt for q in jj])
    _, inl2 = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, 1.0, 0.999)
    print(pair, f"ALIKED kp {len(k1)} {len(k2)} mutual {len(i)} F-inliers(1px) {int(inl.sum())} ({inl.mean():.2f}) time {t1:.2f}s | SIFT mutual {len(ii)} inliers {int(inl2.sum())} ({inl2.mean():.2f})")
