"""OpenCV's SIFT descriptor, computed in torch: the descriptor patches of a build on a GPU.

A SIFT build describes 49 points around every observation of every landmark (the 7 x 7 training
patches, :meth:`favormap.features.sift.SIFTExtractor.sample`): 967,260 descriptors for the fox.
OpenCV computes them on the CPU, one image pyramid per frame and one descriptor after another, which
was half of a GPU build (H200, fox at full resolution: 8.6 of 18.2 s). This module computes the same
descriptors as OpenCV's ``SIFT.compute`` on a torch device, all points of a frame at once:

- the Gaussian pyramid of ``SIFT::detectAndCompute`` (OpenCV 5.0, default parameters) from the
  2x upsampled first octave: bilinear upsampling of the float image, separable Gaussian blurs
  with OpenCV's kernel size and reflect-101 borders, nearest-neighbour halving between octaves;
- ``calcSIFTDescriptor`` for each point in its octave and layer: the rotated 4 x 4 grid of 8-bin
  orientation histograms over a (2r+1)^2 window, OpenCV's ``fastAtan2`` polynomial, trilinear
  interpolation (as hat-function weights: a batched matrix product instead of scatters), the 0.2
  clamp and the rounding to 0..255.

Rounding aside (float sums in another order), the result is OpenCV's descriptor:
``tests/test_sift_torch.py`` compares them point by point. The pyramid goes up to the highest
octave a point uses; the levels the points use go into one flat buffer, and all points of a frame
are described in chunks over it. On a CPU, OpenCV is faster; favormap uses this module only where
the build runs on a GPU (:class:`favormap.features.sift.SIFTExtractor` with a device). The
TF32 switches are process-wide: :func:`describe` turns them off while it runs (a GPU task of the
build runs alone).
"""

from __future__ import annotations

import contextlib
import functools
import math

import numpy as np
import torch

from .sift_octave import LAYERS, SIGMA, unpack_octave

_INIT_SIGMA = 0.5  # the blur OpenCV assumes of the camera's image (SIFT_INIT_SIGMA)
_D, _N = 4, 8  # SIFT_DESCR_WIDTH, SIFT_DESCR_HIST_BINS
_SCL_FCTR, _MAG_THR, _INT_FCTR = 3.0, 0.2, 512.0  # SIFT_DESCR_SCL_FCTR, SIFT_DESCR_MAG_THR, SIFT_INT_DESCR_FCTR
_FLT_EPSILON = float(np.finfo(np.float32).eps)
# cv::fastAtan2's polynomial (degrees)
_ATAN2_POLY = (0.9997878412794807, -0.3258083974640975, 0.1555786518463281, -0.04432655554792128)
_P1, _P3, _P5, _P7 = (c * (180 / math.pi) for c in _ATAN2_POLY)


def _reflect101(n: int, pad: int, device) -> torch.Tensor:
    """Indices of OpenCV's BORDER_REFLECT_101 for positions -pad .. n - 1 + pad."""
    i = torch.arange(-pad, n + pad, device=device)
    if n == 1:
        return torch.zeros_like(i)
    period = 2 * (n - 1)
    i = torch.remainder(i, period)
    return torch.where(i >= n, period - i, i)


@functools.lru_cache(maxsize=64)
def _gaussian_kernel(sigma: float, device: str) -> torch.Tensor:
    """cv::getGaussianKernel at GaussianBlur's size for float images (2 * round(4 sigma) + 1), kept
    on ``device`` (a copy to a GPU waits for the work queued there)."""
    ksize = int(np.rint(sigma * 8 + 1)) | 1
    x = np.arange(ksize, dtype=np.float64) - (ksize - 1) / 2
    k = np.exp(-0.5 / (sigma * sigma) * x * x)
    return torch.tensor(k / k.sum(), dtype=torch.float32, device=device)


def _blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """cv::GaussianBlur(img, Size(), sigma, sigma) of a float (H, W) image: the separable kernel as
    two convolutions (run under :func:`_float32`: a GPU may otherwise convolve in TF32)."""
    k = _gaussian_kernel(sigma, str(img.device))
    pad = (len(k) - 1) // 2
    h, w = img.shape
    x = img[:, _reflect101(w, pad, img.device)][None, None]  # (1, 1, H, W + 2 pad)
    x = torch.nn.functional.conv2d(x, k.view(1, 1, 1, -1))[0, 0]
    x = x[_reflect101(h, pad, img.device)][None, None]  # (1, 1, H + 2 pad, W)
    return torch.nn.functional.conv2d(x, k.view(1, 1, -1, 1))[0, 0]


@contextlib.contextmanager
def _float32():
    """Full float32 products in matrix multiplications and convolutions (not TF32) meanwhile."""
    flags = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = flags


def _upsample2(gray: torch.Tensor) -> torch.Tensor:
    """cv::resize(gray, 2x, INTER_LINEAR) of the grey image as float (OpenCV 5.0 upsamples the float
    image; rounding to 8 bits first, as an 8-bit resize would, left 92 % of the descriptors off by one
    in some bin instead of 0.2 %): every output pixel a mix of quarters of its two nearest inputs."""

    def axis(x: torch.Tensor, dim: int) -> torch.Tensor:
        n = x.shape[dim]
        k = torch.arange(n, device=x.device)
        prev = x.index_select(dim, (k - 1).clamp(min=0))
        nxt = x.index_select(dim, (k + 1).clamp(max=n - 1))
        even, odd = 0.25 * prev + 0.75 * x, 0.75 * x + 0.25 * nxt  # outputs 2k and 2k + 1
        return torch.stack((even, odd), dim + 1).flatten(dim, dim + 1)

    return axis(axis(gray.float(), 1), 0)


def _halve(img: torch.Tensor) -> torch.Tensor:
    """cv::resize(img, Size(w / 2, h / 2), INTER_NEAREST)."""
    h, w = img.shape
    hh, ww = max(h // 2, 1), max(w // 2, 1)
    dev = img.device
    rows = torch.floor(torch.arange(hh, dtype=torch.float64, device=dev) * (h / hh)).long().clamp(max=h - 1)
    cols = torch.floor(torch.arange(ww, dtype=torch.float64, device=dev) * (w / ww)).long().clamp(max=w - 1)
    return img[rows][:, cols]


def _layer_sigmas() -> list[float]:
    """buildGaussianPyramid's incremental blur of layers 1 .. nOctaveLayers."""
    k = 2.0 ** (1.0 / LAYERS)
    out = [SIGMA]
    for i in range(1, LAYERS + 1):
        prev = k ** (i - 1) * SIGMA
        out.append(math.sqrt((prev * k) ** 2 - prev**2))
    return out


def gaussian_pyramid(gray: torch.Tensor, last_octave: int) -> dict[tuple[int, int], torch.Tensor]:
    """OpenCV SIFT's Gaussian pyramid of an 8-bit grey image (H, W) from the upsampled first octave
    (-1) to ``last_octave``, layers 0 .. nOctaveLayers (those a keypoint can sit on, and the one the
    next octave halves): ``{(octave, layer): float image}``."""
    sig = _layer_sigmas()
    pyr: dict[tuple[int, int], torch.Tensor] = {}
    img = _blur(_upsample2(gray), math.sqrt(max(SIGMA**2 - 4 * _INIT_SIGMA**2, 0.01)))
    for o in range(-1, last_octave + 1):
        if o > -1:
            img = _halve(pyr[(o - 1, LAYERS)])
        pyr[(o, 0)] = img
        for i in range(1, LAYERS + 1):
            img = pyr[(o, i)] = _blur(img, sig[i])
    return pyr


def _fast_atan2(y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """cv::fastAtan2 (degrees, [0, 360))."""
    ax, ay = x.abs(), y.abs()
    small = ax >= ay
    c = torch.where(small, ay / (ax + 2.220446049250313e-16), ax / (ay + 2.220446049250313e-16))
    c2 = c * c
    a = (((_P7 * c2 + _P5) * c2 + _P3) * c2 + _P1) * c
    a = torch.where(small, a, 90.0 - a)
    a = torch.where(x < 0, 180.0 - a, a)
    return torch.where(y < 0, 360.0 - a, a)


def _describe_chunk(flat, base, rows, cols, centre, cos_t, sin_t, ori, radius, r_max):
    """calcSIFTDescriptor of M points, each on its own pyramid image (``base``: where it starts in
    ``flat``, ``rows`` x ``cols``; all (M, 1)): (M, 128) float32, rounded to 0..255."""
    dev = flat.device
    off = torch.arange(-r_max, r_max + 1, device=dev)
    ii, jj = torch.meshgrid(off, off, indexing="ij")  # window rows (i) and columns (j)
    ii, jj = ii.reshape(1, -1), jj.reshape(1, -1)
    r = centre[:, 1:2] + ii
    c = centre[:, 0:1] + jj
    ok = (ii.abs() <= radius) & (jj.abs() <= radius) & (r > 0) & (r < rows - 1) & (c > 0) & (c < cols - 1)
    ifl, jfl = ii.float(), jj.float()
    c_rot = jfl * cos_t[:, None] - ifl * sin_t[:, None]
    r_rot = jfl * sin_t[:, None] + ifl * cos_t[:, None]
    rbin = r_rot + (_D // 2 - 0.5)
    cbin = c_rot + (_D // 2 - 0.5)
    rc = base + torch.minimum(r.clamp(min=1), rows - 2) * cols + torch.minimum(c.clamp(min=1), cols - 2)
    at = lambda i: flat[i.clamp(0, len(flat) - 1)]  # noqa: E731  (outside the image: masked by ``ok``)
    dx = at(rc + 1) - at(rc - 1)
    dy = at(rc - cols) - at(rc + cols)
    weight = torch.exp((c_rot * c_rot + r_rot * r_rot) * (-1.0 / (_D * _D * 0.5)))
    mag = torch.sqrt(dx * dx + dy * dy) * weight * ok
    obin = (_fast_atan2(dy, dx) - ori[:, None]) * (_N / 360.0)
    o0 = torch.floor(obin)
    frac = obin - o0
    o0 = torch.remainder(o0.to(torch.int64), _N)
    wo = torch.zeros(rbin.shape + (_N,), dtype=torch.float32, device=dev)
    wo.scatter_(-1, o0[..., None], (mag * (1 - frac))[..., None])
    wo.scatter_add_(-1, torch.remainder(o0 + 1, _N)[..., None], (mag * frac)[..., None])
    k = torch.arange(_D, device=dev, dtype=torch.float32)
    wr = torch.relu(1 - (rbin[..., None] - k).abs())  # (M, P, 4): trilinear weights as hat functions
    wc = torch.relu(1 - (cbin[..., None] - k).abs())
    spatial = (wr[..., :, None] * wc[..., None, :]).flatten(-2)  # (M, P, 16), bin = row * 4 + column
    hist = torch.bmm(spatial.transpose(1, 2), wo).reshape(len(centre), -1)  # (M, 128)
    thr = torch.linalg.vector_norm(hist, dim=1, keepdim=True) * _MAG_THR
    hist = torch.minimum(hist, thr)
    hist = hist * (_INT_FCTR / torch.linalg.vector_norm(hist, dim=1, keepdim=True).clamp(min=_FLT_EPSILON))
    return torch.round(hist).clamp(0, 255)


_BYTES_PER_PIXEL = 400  # a chunk's peak per window pixel, with a margin (measured on the CPU: 250-320 bytes)


def _default_budget(device: torch.device) -> int:
    """Window pixels per chunk: 2^18 on a CPU (chunks that fit its caches are fastest); on a GPU 2^24
    (fewer, larger steps: kernel launches bound the time), at most a quarter of its free memory."""
    if device.type == "cpu":
        return 1 << 18
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        return int(max(1 << 16, min(1 << 24, free // (4 * _BYTES_PER_PIXEL))))
    return 1 << 24


def describe(
    gray: np.ndarray | torch.Tensor,
    xy: np.ndarray,
    size: np.ndarray,
    angle: np.ndarray,
    octave: np.ndarray,
    device: str | torch.device = "cpu",
    budget: int | None = None,
) -> np.ndarray:
    """OpenCV SIFT descriptors (N, 128) float32 (0..255, not normalised) of keypoints at ``xy``
    (N, 2, OpenCV pixel convention) with OpenCV ``size``, ``angle`` (deg) and packed ``octave``
    (octave & 255 | layer << 8) on the 8-bit grey image ``gray``, computed on ``device``:
    what ``cv2.SIFT_create().compute(gray, keypoints)`` returns when the pyramid starts at the
    upsampled octave -1. ``budget``: window pixels per chunk (memory: 250-320 bytes each; None:
    :func:`_default_budget`)."""
    n = len(xy)
    if n == 0:
        return np.zeros((0, 128), np.float32)
    if budget is None:
        budget = _default_budget(torch.device(device))
    oct_, layer, scale = unpack_octave(octave)
    with _float32():
        pyr = gaussian_pyramid(torch.as_tensor(np.ascontiguousarray(gray), device=device), int(oct_.max()))
        # the levels the points use, one after the other in one flat buffer
        level = (oct_ + 1) * (LAYERS + 1) + layer
        used = np.unique(level)
        images = [pyr[(int(v) // (LAYERS + 1) - 1, int(v) % (LAYERS + 1))] for v in used]
        flat = torch.cat([im.reshape(-1) for im in images])
        start = np.concatenate([[0], np.cumsum([im.numel() for im in images])[:-1]])
        shape = np.array([im.shape for im in images], np.int64)
        at = np.searchsorted(used, level)
        rows, cols = shape[at, 0], shape[at, 1]
        # calcDescriptors: the keypoint in its octave's pixels, OpenCV's float32 arithmetic
        pt = np.asarray(xy, np.float32) * scale[:, None]
        hist_width = np.float32(_SCL_FCTR) * (np.asarray(size, np.float32) * scale * np.float32(0.5))
        radius = np.rint(hist_width * np.float32(1.4142135623730951) * np.float32(_D + 1) * np.float32(0.5))
        radius = np.minimum(radius.astype(np.int64), np.sqrt(rows.astype(np.float64) ** 2 + cols**2).astype(np.int64))
        ori = np.float32(360.0) - np.asarray(angle, np.float32)
        ori[np.abs(ori - 360.0) < _FLT_EPSILON] = 0.0
        # points sorted by window (similar windows together: less padding per chunk), sent to the device
        # in two copies (each copy to a GPU waits for the work queued there) and cut into chunks there
        order = np.argsort(radius, kind="stable")
        ints = torch.as_tensor(np.stack([start[at], rows, cols, radius], 1)[order], device=device)  # (N, 4)
        floats = torch.as_tensor(np.concatenate([pt, ori[:, None], hist_width[:, None]], 1)[order], device=device)
        centre = torch.round(floats[:, :2]).to(torch.int64)  # cvRound (half to even)
        ori_t, hw_t = floats[:, 2], floats[:, 3]
        cos_t, sin_t = torch.cos(ori_t * math.radians(1.0)) / hw_t, torch.sin(ori_t * math.radians(1.0)) / hw_t
        out = torch.empty((n, _D * _D * _N), dtype=torch.float32, device=device)
        window = (2 * radius[order] + 1) ** 2  # nondecreasing
        i = 0
        while i < n:  # chunks of at most ``budget`` window pixels (at least one point)
            j = i + max(1, int(np.searchsorted(np.arange(1, n - i + 1) * window[i:], budget, side="right")))
            out[i:j] = _describe_chunk(
                flat,
                *(ints[i:j, k : k + 1] for k in range(3)),
                centre[i:j],
                cos_t[i:j],
                sin_t[i:j],
                ori_t[i:j],
                ints[i:j, 3:4],
                int(radius[order[j - 1]]),
            )
            i = j
    desc = np.empty((n, _D * _D * _N), np.float32)
    desc[order] = out.cpu().numpy()
    return desc
