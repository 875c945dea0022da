"""Thirty-sixth session: tools/bench_accuracy.py with a prototype "warp" stage after the rendering
iterations (same arguments as the tool; variants "rendered warp-K", "mean warp-K" for K = 1, 3).

The warp stage: from the pose the rendering iterations reached, each visible landmark's K mapping
observations nearest in direction are warped into the query by the homography of the landmark's
plane (PlaneAligner's normals) into 128 x 128 tiles centred on its projection; every query keypoint
within RADIUS px of the projection is scored by the cosine between its own descriptor and the mean of
the tiles' SIFT descriptors at the projection, computed in that keypoint's frame (its size, angle,
octave). A landmark takes its best keypoint when the score reaches the extractor's threshold and
the second best is below RATIO x best; a keypoint claimed twice keeps its best landmark. PnP-RANSAC
on those matches, then the weighted final refinement, as the localizer's last iteration. SIFT maps
only; needs the mapping images (the map's provenance folder). Run from the repository root:

    PYTHONPATH=. FAVORMAP_FOX=../shared/data/fox python docs/benchmarks/s36-prototypes/warploc.py \
        --workdir W --splits fox-extrap --priors noise --no-baseline --variants "rendered,rendered warp-1"
"""

import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "tools"))
import bench_accuracy as B  # noqa: E402

from favormap.geometry import from_rigid3d, project  # noqa: E402
from favormap.localize import localizer as L  # noqa: E402
from favormap.localize.align import PlaneAligner  # noqa: E402
from favormap.localize.matching import radius_pairs  # noqa: E402

RADIUS = float(os.environ.get("WARP_RADIUS", 4.0))
RATIO = float(os.environ.get("WARP_RATIO", 0.95))
TILE = 64  # half side
_state = {"k": 0}


class WarpLocalizer(L.Localizer):
    warp_k = 0
    warp_union = False

    def _strong_first(self, feats):
        out = super()._strong_first(feats)
        f = out[0]
        # the reordering (if any) of the keypoints against the extractor's state arrays
        if f is feats:
            self._order = np.arange(len(feats.keypoints))
        else:
            from favormap.features.sift_octave import min_response

            strong = np.asarray(feats.scores) >= min_response(max(self._contrasts()))
            self._order = np.r_[np.flatnonzero(strong), np.flatnonzero(~strong)]
        return out

    def _refine(self, q, start, iters, t, anchor=None):
        res = super()._refine(q, start, iters, t, anchor)
        if not self.warp_k or not res.success:
            return res
        s = time.perf_counter()
        pose = res.cam_from_world
        rows = self._visible(q, pose, t)
        m, sims = self._warp_matches(q, pose, rows)
        if self.warp_union and res.matches is not None:
            # the rendering's last inliers too, where neither their landmark nor their keypoint has a warp match
            r_m = res.matches[res.inlier_mask]
            r_s = res.match_similarity[res.inlier_mask]
            add = ~np.isin(r_m[:, 0], m[:, 0]) & ~np.isin(r_m[:, 1], m[:, 1])
            m, sims = np.r_[m, r_m[add]], np.r_[sims, r_s[add]]
        t["warp"] = time.perf_counter() - s
        if len(m) < 4:
            return res
        ans = self._pnp(q, self.positions[m[:, 0]], m[:, 1], t)
        n_in = int(ans["num_inliers"]) if ans is not None else 0
        if ans is None or n_in < self.config.checks.min_inliers:
            return res
        it = L.IterationResult(from_rigid3d(ans["cam_from_world"]), len(rows), len(m), n_in, True, kind="warp")
        its = list(res.iterations) + [it]
        last = dict(matches=m, inliers=np.asarray(ans["inlier_mask"], bool), similarity=sims)
        cov = self._weighted(q, it, last, t) if self.config.landmark_sigma_px != 0 else None
        out = self._result(q, last, its, t, start)
        out.covariance = cov if out.success else None
        return out

    def _gray(self, f):
        cache = self.__dict__.setdefault("_grays", {})
        if f not in cache:
            from favormap.io import load_image

            al = self._warp_al
            name = self.map.frame_names[f]
            p, cam = al._sequence_frames()[name]
            img, _ = load_image(p, cam, self.map.max_side)
            cache[f] = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        return cache[f]

    def _warp_matches(self, q, pose, rows):
        if getattr(self, "_warp_al", None) is None:
            self._warp_al = PlaneAligner(self.map)
        al = self._warp_al
        K = q.cam.K
        uv = project(K, pose, self.positions[rows])
        kp = q.feats.keypoints
        li, kj = radius_pairs(uv, kp, RADIUS)
        if not len(li):
            return np.zeros((0, 2), np.int64), np.zeros(0)
        lm_u = np.unique(li)  # landmarks (indices into rows) with candidates
        center = -pose[:3, :3].T @ pose[:3, 3]
        obs = al.reference_observations(self.positions, rows[lm_u], center, self.warp_k)
        obs = obs.reshape(len(lm_u), -1)
        tiles, tpos, tl = [], [], []  # tile image, landmark position in the tile, landmark slot
        for a, r in enumerate(rows[lm_u]):
            X = self.positions[r]
            n = al.normals[r]
            c0 = np.floor(uv[lm_u[a]]) - TILE
            Tr = np.array([[1, 0, -c0[0]], [0, 1, -c0[1]], [0, 0, 1.0]])
            for o in obs[a]:
                if o < 0:
                    continue
                f = int(al.obs_frame[o])
                Tf = np.asarray(self.map.cam_from_world[f])
                Rrel = pose[:3, :3] @ Tf[:3, :3].T
                trel = pose[:3, 3] - Rrel @ Tf[:3, 3]
                nr = Tf[:3, :3] @ n
                dr = nr @ (Tf[:3, :3] @ X + Tf[:3, 3])
                H = K @ (Rrel + np.outer(trel, nr) / dr) @ np.linalg.inv(al.K[f])
                tiles.append(cv2.warpPerspective(self._gray(f), Tr @ H, (2 * TILE, 2 * TILE), flags=cv2.INTER_LINEAR))
                tpos.append(uv[lm_u[a]] - c0)
                tl.append(a)
        tl = np.array(tl)
        cols = 32
        nrow = -(-len(tiles) // cols)
        mos = np.zeros((nrow * 2 * TILE, cols * 2 * TILE), np.uint8)
        offs = np.zeros((len(tiles), 2), np.float32)
        for i, tile in enumerate(tiles):
            r_, c_ = divmod(i, cols)
            mos[r_ * 2 * TILE : (r_ + 1) * 2 * TILE, c_ * 2 * TILE : (c_ + 1) * 2 * TILE] = tile
            offs[i] = [c_ * 2 * TILE, r_ * 2 * TILE]
        # (candidate pair, tile) entries: every tile of the pair's landmark
        slot = np.searchsorted(lm_u, li)
        first = np.searchsorted(tl, np.arange(len(lm_u)))
        count = np.bincount(tl, minlength=len(lm_u))
        pe = np.repeat(np.arange(len(li)), count[slot])
        te = np.concatenate([np.arange(first[s_], first[s_] + count[s_]) for s_ in slot]) if len(li) else np.zeros(0, int)
        st = q.feats.dense
        ex = self.extractor
        ko = self._order[kj[pe]]
        pts = (np.array(tpos, np.float32) + offs)[te]

        class S:
            gray = mos

        d = ex._describe(S, pts, st.size[ko], st.angle[ko], st.octave[ko])
        acc = np.zeros((len(li), d.shape[1]))
        np.add.at(acc, pe, d)
        acc /= np.maximum(np.linalg.norm(acc, axis=1, keepdims=True), 1e-12)
        score = np.einsum("ij,ij->i", acc, q.desc[kj])
        # best per landmark with a ratio test, then one landmark per keypoint
        order = np.lexsort((-score, li))
        li_o, kj_o, sc_o = li[order], kj[order], score[order]
        start = np.r_[True, li_o[1:] != li_o[:-1]]
        idx = np.flatnonzero(start)
        second = np.full(len(idx), -np.inf)
        has2 = np.r_[idx[1:], len(li_o)] - idx > 1
        second[has2] = sc_o[idx[has2] + 1]
        thr = self.config.match_threshold if self.config.match_threshold is not None else ex.match_threshold
        keep = (sc_o[idx] >= thr) & (second < RATIO * sc_o[idx])
        bl, bk, bs = li_o[idx][keep], kj_o[idx][keep], sc_o[idx][keep]
        o2 = np.lexsort((-bs, bk))
        u = np.r_[True, bk[o2][1:] != bk[o2][:-1]]
        sel = o2[u]
        return np.c_[rows[bl[sel]], bk[sel]].astype(np.int64), bs[sel]


_orig_cfg = B.localizer_config


def _cfg(over):
    over = dict(over)
    _state["k"] = over.pop("_warp", 0)
    _state["union"] = over.pop("_union", False)
    return _orig_cfg(over)


def _make(*a, **kw):
    loc = WarpLocalizer(*a, **kw)
    loc.warp_k = _state["k"]
    loc.warp_union = _state["union"]
    return loc


import favormap.localize as FL  # noqa: E402

B.localizer_config = _cfg
FL.Localizer = _make
for k in (1, 3):
    B.VARIANTS[f"rendered warp-{k}"] = ("rendered", {"_warp": k})
    B.VARIANTS[f"mean warp-{k}"] = ("mean", {"_warp": k})
    # the rendering's last inliers kept where the warp stage matched neither their landmark nor their keypoint
    B.VARIANTS[f"rendered warpu-{k}"] = ("rendered", {"_warp": k, "_union": True})

if __name__ == "__main__":
    sys.argv[0] = "bench_accuracy.py"
    B.main()
