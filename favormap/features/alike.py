"""ALIKE (IEEE T-MM 2022): keypoints and a dense descriptor map at full resolution from a small
convolutional network; the extractor family of the paper's best 7-Scenes results (ALIKE-l).

The network is favormap's own (:mod:`favormap.features.alike_net`); the published weights of its four
variants ship with favormap (``favormap/features/weights/alike-{t,s,n,l}.pth``, BSD-3-Clause, Zhao
Xiaoming: ``LICENSE-ALIKE`` there) and are read with ``torch.load(weights_only=True)``; nothing touches the
network. A map records only its extractor's name, so each variant is registered under its own name
(``alike-t``, ``alike-s``, ``alike-n``, ``alike-l``; descriptors of 64, 96, 128 and 128 channels) and
``alike`` is :data:`DEFAULT`.

Keypoints are the 5 x 5 maxima of the score map (with the published NMS's two further rounds: the maxima
of what is left once the windows of those found are cleared) above ``score_threshold`` (0.2, the
published demo's), at least 2 px from the border, the ``max_keypoints`` strongest, refined to sub-pixel by the published
soft-argmax (5 x 5 window, temperature 0.1). Descriptors are the unit descriptor map sampled bilinearly
and normalised again, as the published model's: :meth:`ALIKEExtractor.sample` samples the kept map
(float16, H x W x C) at any position, so a descriptor sampled at a keypoint equals the one
:meth:`ALIKEExtractor.extract` returns for it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import FavormapError, InputError
from .alike_net import CONFIGS
from .aliked_net import _bilinear_zeros
from .base import Extractor, ExtractorPolicy, Features, register
from .heatmap import local_maxima, soft_argmax

WEIGHTS = Path(__file__).resolve().parent / "weights"
VARIANTS = tuple(CONFIGS)  # alike-t, alike-s, alike-n, alike-l
# the variant "alike" names: the paper's -l, the slowest on a CPU (about 1.5x -n); "alike-t", "alike-s"
# and "alike-n" name the lighter ones
DEFAULT = "alike-l"


def weights_path(variant: str = DEFAULT) -> Path:
    """The shipped weights of an ALIKE variant; FavormapError (one line) when the file is missing."""
    if variant not in CONFIGS:
        raise InputError(f"unknown ALIKE variant {variant!r} (one of {', '.join(VARIANTS)})")
    path = WEIGHTS / f"{variant}.pth"
    if not path.is_file():
        raise FavormapError(f"the {variant} weights are missing: {path} (they come with favormap; reinstall it)")
    return path


def _load_model(variant: str, device: str):
    from .alike_net import ALNet

    path = weights_path(variant)
    try:
        model = ALNet(variant)
        model.load_state_dict(torch.load(path, map_location="cpu", weights_only=True), strict=True)
    except Exception as e:  # noqa: BLE001 - a damaged or foreign weights file: one line
        why = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise FavormapError(f"cannot load the {variant} weights {path}: {why}") from None
    return model.to(device).eval()


@dataclass
class _AlikeState:
    dmap: torch.Tensor  # (H, W, C) float16: the unit descriptor map that descriptors are sampled from


@register("alike")
class ALIKEExtractor(Extractor):
    variant = DEFAULT
    channels = CONFIGS[DEFAULT][4]
    uses_device = True
    # as ALIKED's: a learned descriptor whose soft-argmax keypoints are sub-pixel but imprecise across views
    policy = ExtractorPolicy(align_patches=20, match_threshold=0.5)
    _models: dict = {}  # (variant, device) -> the network, shared by every extractor of that variant there

    def __init__(
        self, max_keypoints: int = 2048, device: str | None = None, score_threshold: float = 0.2, nms_radius: int = 2
    ):
        super().__init__(max_keypoints, device)
        if not (isinstance(nms_radius, (int, np.integer)) and nms_radius >= 1):
            raise ValueError(f"nms_radius must be an integer >= 1, not {nms_radius!r}")
        self.score_threshold = float(score_threshold)
        self.nms_radius = int(nms_radius)
        key = (self.variant, self.device)
        if key not in ALIKEExtractor._models:
            ALIKEExtractor._models[key] = _load_model(self.variant, self.device)
        self.model = ALIKEExtractor._models[key]

    def config(self) -> dict:
        return {
            **super().config(),
            "weights": self.variant,
            "score_threshold": self.score_threshold,
            "nms_radius": self.nms_radius,
        }

    @torch.inference_mode()
    def extract(self, image: np.ndarray) -> Features:
        h, w = image.shape[:2]
        x = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float().div_(255.0).to(self.device)
        dmap, score = self.model.dense(x)
        s = score[0, 0]
        xy, scores = local_maxima(s, self.nms_radius, self.score_threshold, self.max_keypoints, rounds=2)
        xy = soft_argmax(s, xy, self.nms_radius, temperature=0.1)
        state = _AlikeState(dmap[0].permute(1, 2, 0).to(torch.float16).contiguous())
        kp = (xy + 0.5).cpu().numpy().astype(np.float32)  # COLMAP pixels
        feats = Features(kp, scores.cpu().numpy().astype(np.float32), None, (w, h), state)
        feats.descriptors = self.sample(feats, feats.keypoints)
        return feats

    @classmethod
    def state_arrays(cls, state: _AlikeState) -> dict[str, np.ndarray]:
        return {"descriptor_map": state.dmap.cpu().numpy()}

    @classmethod
    def state_from_arrays(cls, arrays: dict[str, np.ndarray]) -> _AlikeState:
        dmap = arrays.get("descriptor_map")
        if dmap is None or dmap.ndim != 3 or dmap.shape[2] != cls.channels:
            raise InputError(f"this feature cache holds no {cls.variant} features; delete it or name another file")
        return _AlikeState(torch.from_numpy(np.ascontiguousarray(dmap)))

    @torch.inference_mode()
    def sample(self, features: Features, points: np.ndarray) -> np.ndarray:
        """The descriptor map at ``points`` (COLMAP pixels; bilinear, positions clamped to the image),
        normalised to unit length."""
        st: _AlikeState = features.dense
        pts = np.asarray(points, np.float32).reshape(-1, 2)
        if len(pts) == 0:
            return np.zeros((0, self.channels), np.float32)
        W, H = features.image_size
        p = torch.as_tensor(pts) - 0.5
        p = torch.stack([p[:, 0].clamp(0, W - 1), p[:, 1].clamp(0, H - 1)], 1)
        dmap = st.dmap.to(self.device)
        d = _bilinear_zeros(dmap, p.to(dmap.device))  # (inside the map: the zeros never apply)
        return F.normalize(d, dim=1).cpu().numpy().astype(np.float32)


@register("alike-t")
class ALIKETExtractor(ALIKEExtractor):
    variant, channels = "alike-t", CONFIGS["alike-t"][4]


@register("alike-s")
class ALIKESExtractor(ALIKEExtractor):
    variant, channels = "alike-s", CONFIGS["alike-s"][4]


@register("alike-n")
class ALIKENExtractor(ALIKEExtractor):
    variant, channels = "alike-n", CONFIGS["alike-n"][4]


@register("alike-l")
class ALIKELExtractor(ALIKEExtractor):
    variant, channels = "alike-l", CONFIGS["alike-l"][4]
