"""The ALIKE network (Zhao et al., "ALIKE: Accurate and Lightweight Keypoint Detection and Descriptor
Extraction", IEEE T-MM 2022), written for favormap in plain torch.

Module and parameter names follow the published model, so that its weights (``alike-{t,s,n,l}.pth``,
shipped with favormap in ``favormap/features/weights``, BSD-3-Clause: ``LICENSE-ALIKE`` there) load with
``strict=True``.

The network: an encoder of four blocks (full, 1/2, 1/8 and 1/32 resolution: a plain block of two 3 x 3
convolutions, then three residual blocks, max pooling between them), whose outputs are projected to
dim / 4 channels each (1 x 1, ReLU), upsampled to full resolution (bilinear, corners aligned) and
concatenated into a dim-channel map; a 1 x 1 head (two layers in the large variant) turns it into dim
descriptor channels and one score channel. The descriptor map is L2-normalised per pixel, the score map
goes through a sigmoid."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

# (c1, c2, c3, c4, dim, single_head) of the published configurations (c4 == dim: the last projection
# takes dim channels)
CONFIGS = {
    "alike-t": (8, 16, 32, 64, 64, True),
    "alike-s": (8, 16, 48, 96, 96, True),
    "alike-n": (16, 32, 64, 128, 128, True),
    "alike-l": (32, 64, 128, 128, 128, False),
}


def _conv3(cin: int, cout: int) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, 1, 1, bias=False)


class ConvBlock(nn.Module):
    """Two 3 x 3 convolutions, each followed by batch normalisation and ReLU."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.conv1, self.bn1 = _conv3(cin, cout), nn.BatchNorm2d(cout)
        self.conv2, self.bn2 = _conv3(cout, cout), nn.BatchNorm2d(cout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(self.bn2(self.conv2(F.relu(self.bn1(self.conv1(x))))))


class ResBlock(nn.Module):
    """A residual block: two 3 x 3 convolutions with batch normalisation, the input added through a
    1 x 1 convolution (the channels change), ReLU."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.conv1, self.bn1 = _conv3(cin, cout), nn.BatchNorm2d(cout)
        self.conv2, self.bn2 = _conv3(cout, cout), nn.BatchNorm2d(cout)
        self.downsample = nn.Conv2d(cin, cout, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.bn2(self.conv2(F.relu(self.bn1(self.conv1(x)))))
        return F.relu(out + self.downsample(x))


class ALNet(nn.Module):
    def __init__(self, config: str = "alike-n"):
        super().__init__()
        c1, c2, c3, c4, dim, single_head = CONFIGS[config]
        self.dim = dim
        self.block1 = ConvBlock(3, c1)
        self.block2 = ResBlock(c1, c2)
        self.block3 = ResBlock(c2, c3)
        self.block4 = ResBlock(c3, c4)
        self.conv1 = nn.Conv2d(c1, dim // 4, 1, bias=False)
        self.conv2 = nn.Conv2d(c2, dim // 4, 1, bias=False)
        self.conv3 = nn.Conv2d(c3, dim // 4, 1, bias=False)
        self.conv4 = nn.Conv2d(dim, dim // 4, 1, bias=False)
        self.convhead1 = None if single_head else nn.Conv2d(dim, dim, 1, bias=False)
        self.convhead2 = nn.Conv2d(dim, dim + 1, 1, bias=False)

    def dense(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``image`` (1, 3, H, W) RGB in [0, 1] -> the unit descriptor map (1, dim, H, W) and the score map
        (1, 1, H, W) in (0, 1). The image is padded with zeros at its bottom and right to multiples of 32
        (as the published model) and the maps cropped back."""
        h, w = image.shape[-2:]
        ph, pw = (-h) % 32, (-w) % 32
        x = F.pad(image, (0, pw, 0, ph)) if ph or pw else image
        x1 = self.block1(x)
        x2 = self.block2(F.max_pool2d(x1, 2))
        x3 = self.block3(F.max_pool2d(x2, 4))
        x4 = self.block4(F.max_pool2d(x3, 4))
        parts = [F.relu(self.conv1(x1))]
        for conv, feat, scale in ((self.conv2, x2, 2), (self.conv3, x3, 8), (self.conv4, x4, 32)):
            parts.append(F.interpolate(F.relu(conv(feat)), scale_factor=scale, mode="bilinear", align_corners=True))
        x1234 = torch.cat(parts, 1)
        if self.convhead1 is not None:
            x1234 = F.relu(self.convhead1(x1234))
        out = self.convhead2(x1234)[..., :h, :w]
        return F.normalize(out[:, :-1], dim=1), torch.sigmoid(out[:, -1:])
