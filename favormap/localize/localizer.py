"""Iterative render -> match -> PnP-RANSAC localization (paper secs. 3.3-3.4).

From the current pose estimate (initially the prior): select the landmarks visible from it through
the spatial index, read their voxel grids lazily, render their descriptors along the rays from the
camera centre (one batched call), match them to the query's features (similarity matrix,
threshold, best query feature per rendered descriptor) and solve PnP with pycolmap's LO-RANSAC +
refinement. Repeat from the new estimate until it stops moving or ``iterations`` is reached.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from .. import features as feats_mod
from ..errors import InputError, LocalizationFailed
from ..geometry import camera_centers, from_rigid3d, pose_error
from ..io import Camera, prepare_image, read_rgb
from ..mapfile import Map
from ..ops.spatial import SpatialIndex, ViewLimits, visible_rows
from ..voxels import render_from_camera


@dataclass
class LocalizeConfig:
    iterations: int = 3
    match_threshold: float = 0.7  # cosine similarity (paper's reference config)
    mutual: bool = False  # also require the rendered descriptor to be the query feature's best
    max_keypoints: int = 4096
    ransac_max_error_px: float = 8.0
    min_inliers: int = 12
    stop_translation: float = 1e-4  # relative to the median landmark distance
    stop_rotation_deg: float = 0.01
    descriptors: str = "rendered"  # "rendered" (FaVoR) or "mean" (baseline: mean observed descriptor)
    view_limits: ViewLimits = field(default_factory=ViewLimits)
    device: str = "cpu"
    seed: int = 0


@dataclass
class IterationResult:
    cam_from_world: np.ndarray
    num_visible: int
    num_matches: int
    num_inliers: int
    success: bool


@dataclass
class LocalizationResult:
    success: bool
    cam_from_world: np.ndarray  # final estimate (the prior when not successful)
    num_matches: int
    num_inliers: int
    iterations: list[IterationResult]
    timings: dict[str, float]
    message: str = ""
    # for visualisation / analysis (last iteration)
    keypoints: np.ndarray | None = None
    matches: np.ndarray | None = None  # (K, 2) [landmark row, query keypoint]
    inlier_mask: np.ndarray | None = None
    match_similarity: np.ndarray | None = None  # (K,) cosine of rendered vs query descriptor per match

    def to_json(self) -> dict:
        from ..geometry import inverse, rotmat_to_quat

        T = self.cam_from_world
        return {
            "success": bool(self.success),
            "message": self.message,
            "world_from_cam": inverse(T).tolist(),
            "cam_from_world": {"quaternion_xyzw": rotmat_to_quat(T[:3, :3]).tolist(), "translation": T[:3, 3].tolist()},
            "num_matches": int(self.num_matches),
            "num_inliers": int(self.num_inliers),
            "iterations": [
                {"cam_from_world": it.cam_from_world.tolist(), "num_visible": it.num_visible, "num_matches": it.num_matches,
                 "num_inliers": it.num_inliers, "success": it.success}
                for it in self.iterations
            ],
            "timings": {k: round(v, 5) for k, v in self.timings.items()},
        }


def match_descriptors(rendered: torch.Tensor, query: torch.Tensor, threshold: float, mutual: bool = False) -> np.ndarray:
    """(K, 2) index pairs [rendered row, query row]: for every rendered descriptor the most similar
    query descriptor, kept when the cosine similarity reaches ``threshold``."""
    if len(rendered) == 0 or len(query) == 0:
        return np.zeros((0, 2), np.int64)
    sim = rendered @ query.T
    best_sim, best = sim.max(1)
    ok = best_sim >= threshold
    if mutual:
        ok &= sim.argmax(0)[best] == torch.arange(len(rendered), device=sim.device)
    idx = torch.nonzero(ok).squeeze(1)
    return torch.stack([idx, best[idx]], 1).cpu().numpy()


class Localizer:
    """Localizes query images against one map; keep it alive to localize many queries."""

    def __init__(self, map_: Map | str, config: LocalizeConfig = LocalizeConfig()):
        self.map = map_ if isinstance(map_, Map) else Map.open(map_)
        self.config = config
        self.extractor = feats_mod.create(self.map.extractor, max_keypoints=config.max_keypoints,
                                          device=None if config.device == "cpu" else config.device)
        self.index = SpatialIndex(self.map.positions)
        self.default_camera = self.map.cameras[int(self.map.frame_camera_ids[0])] if self.map.num_frames else next(iter(self.map.cameras.values()))
        self.scale = float(np.median(self.map.depth_range[:, 0])) if len(self.map) else 1.0

    def close(self):
        self.map.close()

    # -- inputs --------------------------------------------------------------------------------------
    def prepare(self, image, camera: Camera | None = None):
        """Query image (path or RGB array at the camera's resolution) -> (working image, pinhole camera)."""
        camera = camera or self.default_camera
        img = read_rgb(image) if not isinstance(image, np.ndarray) else image
        h, w = img.shape[:2]
        if (w, h) != (camera.width, camera.height):
            if (w, h) == (camera.height, camera.width):
                raise InputError(f"query image is {w}x{h} but the camera is {camera.width}x{camera.height} (rotated?)")
            if abs(w / h - camera.width / camera.height) > 0.01:
                raise InputError(f"query image is {w}x{h} but the camera is {camera.width}x{camera.height}; give --camera")
            camera = camera.scaled(w, h)  # same camera at another resolution
        return prepare_image(img, camera, self.map.max_side)

    # -- main loop -----------------------------------------------------------------------------------
    def localize(self, image, prior_cam_from_world: np.ndarray, camera: Camera | None = None) -> LocalizationResult:
        import pycolmap

        cfg = self.config
        prior = np.asarray(prior_cam_from_world, np.float64)
        if prior.shape != (4, 4) or not np.all(np.isfinite(prior)):
            raise InputError("the prior pose must be a finite 4x4 matrix")
        R = prior[:3, :3]
        if abs(np.linalg.det(R) - 1) > 1e-3 or np.abs(R @ R.T - np.eye(3)).max() > 1e-3:
            raise InputError("the prior pose is not a rigid transform (rotation not orthonormal)")
        t = {k: 0.0 for k in ("extraction", "visibility", "loading", "rendering", "matching", "pnp")}
        t0 = time.perf_counter()
        img, cam = self.prepare(image, camera)
        feats = self.extractor.extract(img)
        qdesc = torch.as_tensor(feats.descriptors, device=cfg.device)
        t["extraction"] = time.perf_counter() - t0
        pc_cam = cam.to_pycolmap()
        est = pycolmap.AbsolutePoseEstimationOptions()
        est.ransac.max_error = cfg.ransac_max_error_px
        est.ransac.random_seed = cfg.seed
        ref = pycolmap.AbsolutePoseRefinementOptions()

        pose = prior.copy()
        iters: list[IterationResult] = []
        last = dict(matches=np.zeros((0, 2), np.int64), inliers=None)
        success = False
        for _ in range(cfg.iterations):
            s = time.perf_counter()
            rows = visible_rows(self.index, cam, pose, self.map.view_dir, self.map.view_angle, self.map.depth_range, cfg.view_limits)
            t["visibility"] += time.perf_counter() - s
            rend = self._descriptors(rows, pose, t)
            s = time.perf_counter()
            m = match_descriptors(rend, qdesc, cfg.match_threshold, cfg.mutual)
            sims = (rend[m[:, 0]] * qdesc[m[:, 1]]).sum(-1).cpu().numpy() if len(m) else np.zeros(0, np.float32)
            t["matching"] += time.perf_counter() - s
            s = time.perf_counter()
            ok = False
            n_in = 0
            if len(m) >= 4:
                ans = pycolmap.estimate_and_refine_absolute_pose(
                    feats.keypoints[m[:, 1]].astype(np.float64), self.map.positions[rows[m[:, 0]]], pc_cam, est, ref)
                if ans is not None:
                    n_in = int(ans["num_inliers"])
                    ok = n_in >= cfg.min_inliers
                    if ok:
                        new_pose = from_rigid3d(ans["cam_from_world"])
                        last = dict(matches=np.c_[rows[m[:, 0]], m[:, 1]], inliers=np.asarray(ans["inlier_mask"], bool),
                                    similarity=sims)
            t["pnp"] += time.perf_counter() - s
            iters.append(IterationResult(new_pose if ok else pose, len(rows), len(m), n_in, ok))
            if not ok:
                break
            success = True
            dt, dr = pose_error(new_pose, pose)
            pose = new_pose
            if dt < cfg.stop_translation * self.scale and dr < cfg.stop_rotation_deg:
                break
        final = [it for it in iters if it.success]
        msg = "" if success else (
            f"too few matches ({iters[-1].num_matches} matches, {iters[-1].num_inliers} inliers, "
            f"{iters[-1].num_visible} visible landmarks; need {cfg.min_inliers} inliers)")
        return LocalizationResult(
            success=success,
            cam_from_world=final[-1].cam_from_world if final else prior,
            num_matches=final[-1].num_matches if final else iters[-1].num_matches,
            num_inliers=final[-1].num_inliers if final else iters[-1].num_inliers,
            iterations=iters, timings=t, message=msg,
            keypoints=feats.keypoints, matches=last["matches"], inlier_mask=last["inliers"],
            match_similarity=last.get("similarity"))

    def _descriptors(self, rows: np.ndarray, pose: np.ndarray, t: dict) -> torch.Tensor:
        """Rendered (or, for the baseline, mean observed) descriptors of landmark rows."""
        dev = self.config.device
        if self.config.descriptors == "mean":
            s = time.perf_counter()
            d = torch.as_tensor(self.map.mean_descriptors(rows), device=dev)
            t["loading"] += time.perf_counter() - s
            return torch.nn.functional.normalize(d, dim=-1)
        s = time.perf_counter()
        desc, dens = self.map.voxels(rows)
        t["loading"] += time.perf_counter() - s
        s = time.perf_counter()
        with torch.no_grad():
            out = render_from_camera(
                torch.as_tensor(desc, device=dev), torch.as_tensor(dens, device=dev),
                torch.as_tensor(self.map.positions[rows], dtype=torch.float32, device=dev),
                torch.as_tensor(self.map.voxel_size[rows], device=dev),
                torch.as_tensor(camera_centers(pose), dtype=torch.float32, device=dev),
                self.map.render_samples)
        t["rendering"] += time.perf_counter() - s
        return out


def localize(map_, image, prior_cam_from_world, camera: Camera | None = None, config: LocalizeConfig = LocalizeConfig()) -> LocalizationResult:
    """One-shot convenience wrapper around :class:`Localizer`."""
    loc = Localizer(map_, config)
    try:
        return loc.localize(image, prior_cam_from_world, camera)
    finally:
        if not isinstance(map_, Map):
            loc.close()


def require_success(result: LocalizationResult) -> LocalizationResult:
    if not result.success:
        raise LocalizationFailed(result.message)
    return result


