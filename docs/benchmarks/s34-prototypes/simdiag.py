"""Is the match similarity (rendered vs mean) predictive of the inlier keypoint's error at the true pose?"""
import sys, dataclasses as dc, numpy as np
from pathlib import Path
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[3] / "tools"))
import bench_accuracy as B
from favormap.build import BuildConfig
from favormap.localize import Localizer, make_source
from favormap.localize.evaluate import EvalConfig, make_priors
from favormap.geometry import project
from favormap.mapfile import Map
from scipy.stats import spearmanr

ext = sys.argv[1] if len(sys.argv) > 1 else "sift"
align = "align" in sys.argv
split = B.fox_splits(["fox-extrap"])[0]
cfg = BuildConfig(extractor=ext) if ext != "sift" else BuildConfig()
path, bs = B.build_or_load(split, Path(__import__("os").environ.get("WORKDIR", "/tmp/w34")), cfg, True, "" if ext == "sift" else "-" + ext)
print("built", bs)
m = Map.open(path)
priors = make_priors(split.queries, m.cam_from_world, EvalConfig(prior_mode="noise", seed=0))
out = {}
for src in ["rendered", "mean"]:
    lc = dc.replace(B.localizer_config({"align": align}), descriptors=src)
    loc = Localizer(m, lc, descriptor_source=make_source(src, m, "cpu", None))
    rs, ss, qs, errs = [], [], [], []
    for i, fr in enumerate(split.queries.frames):
        cam = split.queries.cameras[fr.camera_id]
        res = loc.localize(fr.image_path, priors[i], cam)
        if not res.success:
            errs.append(np.inf); continue
        c_est = -res.cam_from_world[:3, :3].T @ res.cam_from_world[:3, 3]
        c_gt = -fr.cam_from_world[:3, :3].T @ fr.cam_from_world[:3, 3]
        errs.append(np.linalg.norm(c_est - c_gt))
        inl = res.matches[res.inlier_mask]
        kp = res.keypoints[inl[:, 1]]
        if align and res.aligned is not None:
            a = res.aligned[res.inlier_mask]
            ok = np.isfinite(a[:, 0]); kp = np.where(ok[:, None], a, kp)
        uv = project(res.camera.K, fr.cam_from_world, loc.positions[inl[:, 0]])
        r = np.linalg.norm(kp - uv, axis=1)
        s = res.match_similarity[res.inlier_mask]
        rs.append(r); ss.append(s); qs.append(np.full(len(r), i))
        rho = spearmanr(r, -s).statistic
        print(f"{src} q{i} n={len(r)} err={errs[-1]:.4f} rho(|r|,1-s)={rho:+.3f} med|r|={np.median(r):.2f}", flush=True)
    r, s = np.concatenate(rs), np.concatenate(ss)
    # within-query ranks: remove per-query offsets
    rho_q = np.nanmedian([spearmanr(a, -b).statistic for a, b in zip(rs, ss)])
    # residual by similarity quartile within each query
    qr = []
    for a, b in zip(rs, ss):
        q = np.quantile(b, [0.25, 0.5, 0.75]); k = np.searchsorted(q, b)
        qr.append([np.median(a[k == j]) if (k == j).any() else np.nan for j in range(4)])
    print(f"== {src}: median err {np.median(errs):.4f}; pooled rho {spearmanr(r, -s).statistic:+.3f}; per-query median rho {rho_q:+.3f}; "
          f"median |r| by similarity quartile (low..high) {np.nanmedian(np.array(qr), axis=0).round(3)}", flush=True)
    out[src] = (rs, ss, errs)
np.save(f"{__import__("os").environ.get("WORKDIR", "/tmp/w34")}/simdiag-{ext}{'-align' if align else ''}.npy", np.array(out, dtype=object), allow_pickle=True)
