"""Procedural textures of the synthetic room (smooth colour noise, shapes, glyphs) and the atlas
that packs them into one image for rendering."""

from __future__ import annotations

import string

import cv2
import numpy as np

_ATLAS_WIDTH = 4096
_ATLAS_PAD = 2

_FONTS = [
    cv2.FONT_HERSHEY_SIMPLEX,
    cv2.FONT_HERSHEY_DUPLEX,
    cv2.FONT_HERSHEY_COMPLEX,
    cv2.FONT_HERSHEY_TRIPLEX,
    cv2.FONT_HERSHEY_PLAIN,
    cv2.FONT_HERSHEY_SCRIPT_SIMPLEX,
]
_CHARS = string.ascii_letters + string.digits + "#%&@?+"


def _smooth_noise(
    h: int, w: int, rng: np.random.Generator, base, amplitude: float, finest: float = 2.5, decay: float = 0.72
) -> np.ndarray:
    """Multi-octave smooth colour noise ``base + amplitude * noise`` as (h,w,3) uint8, the noise
    with zero mean and unit std: white noise added at every level of a pyramid that is upsampled
    by 2 per level (coarsest cell ~ half the texture, finest ~``finest`` texels), each octave with
    its own random colour mix."""
    levels = max(1, int(np.floor(np.log2(max(h, w) / 2.0 / finest))) + 1)
    gh, gw = int(np.ceil(h / finest / 2 ** (levels - 1))) + 2, int(np.ceil(w / finest / 2 ** (levels - 1))) + 2
    acc = None
    amp = 1.0
    for _ in range(levels):
        g = rng.random((gh, gw, 3), dtype=np.float32) - np.float32(0.5)
        g = cv2.transform(g, (amp * rng.normal(size=(3, 3))).astype(np.float32))
        acc = g if acc is None else g + cv2.resize(acc, (gw, gh), interpolation=cv2.INTER_CUBIC)
        gh, gw = 2 * gh, 2 * gw
        amp *= decay
    mean, std = cv2.meanStdDev(acc)
    k = amplitude / (float(np.sqrt(np.mean(std**2))) + 1e-6)
    M = np.concatenate([np.eye(3) * k, (np.asarray(base, float) - k * mean.reshape(3))[:, None]], axis=1)
    small = np.clip(cv2.transform(acc, M.astype(np.float32)), 0, 255).astype(np.uint8)
    # finest grid -> texels: one grid cell is ``finest`` texels; random sub-cell offset
    oy, ox = rng.uniform(0, 1, 2)
    A = np.array([[1 / finest, 0, ox], [0, 1 / finest, oy]], np.float32)
    return cv2.warpAffine(small, A, (w, h), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT)


def make_texture(width: int, height: int, rng: np.random.Generator, texels_per_unit: float = 400.0) -> np.ndarray:
    """A procedural RGB uint8 texture with rich, non-repetitive detail at many scales: smooth
    multi-octave colour noise overlaid with random ellipses, rectangles, polygons, lines, circles
    and text.  Deterministic given the generator state."""
    h, w = int(height), int(width)
    tpu = float(texels_per_unit)
    palette = rng.uniform(40, 215, (4, 3))  # a per-texture palette so faces look different
    base = palette[0]
    img = _smooth_noise(h, w, rng, base, float(rng.uniform(22, 38)))

    def colours(k):
        c = palette[rng.integers(0, len(palette), k)] + rng.normal(0, 35, (k, 3))
        wild = rng.random(k) < 0.35  # fully random colours
        c[wild] = rng.uniform(0, 255, (int(wild.sum()), 3))
        ext = rng.random(k) < 0.2  # very dark / very bright for contrast
        c[ext] = np.where(rng.random((int(ext.sum()), 1)) < 0.5, 20.0, 235.0) + rng.normal(0, 10, (int(ext.sum()), 3))
        return np.clip(c, 0, 255).astype(int).tolist()

    area_units = (h * w) / tpu**2
    n = int(100 * area_units) + 8
    # shape sizes (half extents, texels) log-uniform from ~6 mm to ~20 cm, largest first
    rmin, rmax = max(2.0, 0.006 * tpu), max(4.0, 0.2 * tpu)
    r_all = np.sort(np.exp(rng.uniform(np.log(rmin), np.log(rmax), n)))[::-1]
    cx_all = rng.uniform(-r_all, w + r_all)
    cy_all = rng.uniform(-r_all, h + r_all)
    kind_all = rng.random(n)
    filled_all = rng.random(n) < 0.7
    ang_all = rng.uniform(0, np.pi, n)
    asp_all = rng.uniform(0.2, 1.0, n)
    u_all = rng.random(n)
    col_all = colours(n)
    aa = cv2.LINE_AA
    for i in range(n):
        r, cx, cy, kind, a = float(r_all[i]), float(cx_all[i]), float(cy_all[i]), kind_all[i], float(ang_all[i])
        col = tuple(col_all[i])
        filled = bool(filled_all[i])
        thick = -1 if filled else 1 + int(u_all[i] * max(1.0, r / 6))
        if kind < 0.3:
            axes = (max(1, int(r)), max(1, int(r * asp_all[i])))
            cv2.ellipse(img, (int(cx), int(cy)), axes, np.degrees(a), 0, 360, col, thick, aa)
        elif kind < 0.55:
            hw, hh = r, r * asp_all[i]
            ca, sa = np.cos(a), np.sin(a)
            pts = np.array([[-hw, -hh], [hw, -hh], [hw, hh], [-hw, hh]]) @ np.array([[ca, sa], [-sa, ca]])
            pts = (pts + [cx, cy]).astype(np.int32)
            if filled:
                cv2.fillPoly(img, [pts], col, aa)
            else:
                cv2.polylines(img, [pts], True, col, thick, aa)
        elif kind < 0.7:
            k = 3 + int(u_all[i] * 4)
            angs = a * 2 + np.cumsum(rng.uniform(0.5, 1.0, k)) * (2 * np.pi / k)
            rad = r * rng.uniform(0.4, 1.0, k)
            pts = np.stack([cx + rad * np.cos(angs), cy + rad * np.sin(angs)], 1).astype(np.int32)
            if filled:
                cv2.fillPoly(img, [pts], col, aa)
            else:
                cv2.polylines(img, [pts], True, col, thick, aa)
        elif kind < 0.85:
            dx, dy = np.cos(a) * r * 1.5, np.sin(a) * r * 1.5
            cv2.line(
                img,
                (int(cx - dx), int(cy - dy)),
                (int(cx + dx), int(cy + dy)),
                col,
                1 + int(u_all[i] * max(1.0, r / 5)),
                aa,
            )
        else:
            cv2.circle(img, (int(cx), int(cy)), max(1, int(r)), col, thick, aa)

    # text at several sizes (scale 1 ~ 22 texels high ~ 5.5 cm at 400 texels per unit)
    m = int(35 * area_units) + 3
    lens = rng.integers(2, 7, m)
    chars = rng.integers(0, len(_CHARS), int(lens.sum()))
    fonts = rng.integers(0, len(_FONTS), m)
    scales = np.exp(rng.uniform(np.log(0.35), np.log(2.2), m)) * tpu / 400.0
    thicks = rng.integers(1, 4, m)
    ox = rng.integers(-20, w, m)
    oy = rng.integers(0, h + 20, m)
    tcol = colours(m)
    pos = 0
    for i in range(m):
        s = "".join(_CHARS[c] for c in chars[pos : pos + lens[i]])
        pos += lens[i]
        cv2.putText(
            img,
            s,
            (int(ox[i]), int(oy[i])),
            _FONTS[int(fonts[i])],
            float(scales[i]),
            tuple(tcol[i]),
            int(thicks[i]),
            aa,
        )
    return img


def _pack_atlas(textures: list) -> tuple[np.ndarray, np.ndarray]:
    """Shelf-pack textures into one atlas image (edge-replicated padding against bleeding)."""
    p = _ATLAS_PAD
    order = sorted(range(len(textures)), key=lambda i: -textures[i].shape[0])
    width = max(_ATLAS_WIDTH, max(t.shape[1] for t in textures) + 2 * p)
    offsets = np.zeros((len(textures), 2), np.float32)
    x = y = shelf_h = 0
    places = {}
    for i in order:
        th, tw = textures[i].shape[:2]
        if x + tw + 2 * p > width:
            x, y, shelf_h = 0, y + shelf_h, 0
        places[i] = (x, y)
        shelf_h = max(shelf_h, th + 2 * p)
        x += tw + 2 * p
    atlas = np.zeros((y + shelf_h, width, 3), np.uint8)
    for i, (x, y) in places.items():
        th, tw = textures[i].shape[:2]
        atlas[y : y + th + 2 * p, x : x + tw + 2 * p] = cv2.copyMakeBorder(
            textures[i], p, p, p, p, cv2.BORDER_REPLICATE
        )
        offsets[i] = (x + p, y + p)
    return atlas, offsets
