"""Procedural textures of the synthetic room (smooth colour noise, shapes, glyphs) and the atlas
that packs them into one image for rendering."""

from __future__ import annotations

import string

import cv2
import numpy as np

_ATLAS_WIDTH = 4096
_ATLAS_PAD = 2

# The texts' glyphs are the project's own strokes, drawn with cv2.polylines: cv2.putText's glyphs are OpenCV's
# fonts, which changed between releases (OpenCV 5.1 draws them otherwise), and every synthetic scene, test figure
# and benchmark record would change with them. Each glyph is a set of polylines on a grid of 5 x 9 points, written
# as digit pairs "xy": x 0..4, y 0 (cap height) .. 6 (baseline) .. 8 (descender); strokes are separated by spaces.
_GLYPHS = {
    "A": "062046 1333", "B": "0006 003041423303 3344453606", "C": "4130100105163645",
    "D": "0006 003041453606", "E": "40000646 0333", "F": "400006 0333", "G": "41301001051636454323",
    "H": "0006 4046 0343", "I": "1030 2026 1636", "J": "4045361605", "K": "0006 4004 1346", "L": "000646",
    "M": "0600234046", "N": "06004640", "O": "103041453616050110", "P": "06003041423303",
    "Q": "103041453616050110 2446", "R": "06003041423303 2346", "S": "413010010213334445361605",
    "T": "0040 2026", "U": "000516364540", "V": "002640", "W": "0016233640", "X": "0046 4006",
    "Y": "0023 4023 2326", "Z": "00400646",
    "a": "12324346 441405163645", "b": "0006 0312324345361605", "c": "4332120305163645",
    "d": "4046 4332120305163645", "e": "044443321203051636", "f": "41302126 1232",
    "g": "4332120304153544 4247381807", "h": "0006 0312324346", "i": "2226 2020", "j": "3237281807 3030",
    "k": "0006 4205 1446", "l": "10202536", "m": "0206 03122326 23324346", "n": "0206 0312324346",
    "o": "123243453616050312", "p": "0208 0312324345361605", "q": "4248 4332120305163645", "r": "0206 04223243",
    "s": "43321203143445361605", "t": "10152636 0232", "u": "0205163645 4246", "v": "022642",
    "w": "0216243642", "x": "0246 4206", "y": "0224 421808", "z": "02420646",
    "0": "103041453616050110 4105", "1": "112026 1636", "2": "01103041420646", "3": "01103041423313 334445361605",
    "4": "36300444", "5": "400002324345361605", "6": "413010010516364544331304", "7": "004016",
    "8": "130201103041423313 1304051636454433", "9": "423313020110304145361605",
    "#": "1016 3036 0242 0444", "%": "0640 0010110100 3545463635", "&": "4612112031320405162643",
    "@": "32221314253532 35454130100105163646", "?": "0110304142332324 2626", "+": "2125 0343",
}  # fmt: skip
_CHARS = string.ascii_letters + string.digits + "#%&@?+"
_STROKES = {
    c: [np.array([int(d) for d in stroke], np.float64).reshape(-1, 2) for stroke in g.split()]
    for c, g in _GLYPHS.items()
}
# text styles (the fonts of the texts): horizontal stretch and slant of the glyphs
_STYLES = [(1.0, 0.0), (1.15, 0.0), (0.85, 0.0), (1.3, 0.0), (1.0, 0.25), (0.9, 0.4)]
_ADVANCE = 6  # grid units from one glyph to the next
_CAP = 3.5  # texels per grid unit at scale 1: 21-texel capitals, the size of OpenCV's Hershey fonts


def draw_text(img: np.ndarray, text: str, origin, scale: float, style: int, colour, thickness: int) -> None:
    """Draw ``text`` into ``img`` in place with the textures' stroke glyphs (``origin`` is the first glyph's
    bottom-left corner on the baseline, as in cv2.putText; anti-aliased, sub-pixel positions)."""
    stretch, slant = _STYLES[style]
    u = _CAP * scale
    strokes = []
    for i, c in enumerate(text):
        for p in _STROKES[c]:
            x = origin[0] + u * (stretch * (i * _ADVANCE + p[:, 0]) + slant * (6 - p[:, 1]))
            y = origin[1] + u * (p[:, 1] - 6)
            strokes.append(np.round(np.stack([x, y], 1) * 16).astype(np.int32))
    cv2.polylines(img, strokes, False, colour, thickness, cv2.LINE_AA, shift=4)


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
    area_units = (h * w) / tpu**2
    _draw_shapes(img, rng, palette, tpu, int(100 * area_units) + 8)
    _draw_texts(img, rng, palette, tpu, int(35 * area_units) + 3)
    return img


def _colours(rng: np.random.Generator, palette: np.ndarray, k: int) -> list:
    """``k`` RGB colours: the palette's with noise, a share fully random, a share very dark or bright."""
    c = palette[rng.integers(0, len(palette), k)] + rng.normal(0, 35, (k, 3))
    wild = rng.random(k) < 0.35  # fully random colours
    c[wild] = rng.uniform(0, 255, (int(wild.sum()), 3))
    ext = rng.random(k) < 0.2  # very dark / very bright for contrast
    c[ext] = np.where(rng.random((int(ext.sum()), 1)) < 0.5, 20.0, 235.0) + rng.normal(0, 10, (int(ext.sum()), 3))
    return np.clip(c, 0, 255).astype(int).tolist()


def _draw_shapes(img: np.ndarray, rng: np.random.Generator, palette: np.ndarray, tpu: float, n: int) -> None:
    """``n`` random ellipses, rectangles, polygons, lines and circles, largest first."""
    h, w = img.shape[:2]
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
    col_all = _colours(rng, palette, n)
    for i in range(n):
        r, cx, cy, a = float(r_all[i]), float(cx_all[i]), float(cy_all[i]), float(ang_all[i])
        _draw_shape(img, rng, kind_all[i], r, cx, cy, a, asp_all[i], u_all[i], tuple(col_all[i]), bool(filled_all[i]))


def _draw_shape(img, rng, kind: float, r: float, cx: float, cy: float, a: float, asp, u, col: tuple, filled: bool):
    """One shape of size ``r`` at (cx, cy) turned by ``a``: which one ``kind`` (uniform in [0, 1)) says."""
    aa = cv2.LINE_AA
    thick = -1 if filled else 1 + int(u * max(1.0, r / 6))
    if kind < 0.3:
        axes = (max(1, int(r)), max(1, int(r * asp)))
        cv2.ellipse(img, (int(cx), int(cy)), axes, np.degrees(a), 0, 360, col, thick, aa)
    elif kind < 0.7:
        if kind < 0.55:  # a rectangle
            hw, hh = r, r * asp
            ca, sa = np.cos(a), np.sin(a)
            pts = np.array([[-hw, -hh], [hw, -hh], [hw, hh], [-hw, hh]]) @ np.array([[ca, sa], [-sa, ca]])
            pts = (pts + [cx, cy]).astype(np.int32)
        else:  # a polygon of 3 to 6 corners
            k = 3 + int(u * 4)
            angs = a * 2 + np.cumsum(rng.uniform(0.5, 1.0, k)) * (2 * np.pi / k)
            rad = r * rng.uniform(0.4, 1.0, k)
            pts = np.stack([cx + rad * np.cos(angs), cy + rad * np.sin(angs)], 1).astype(np.int32)
        if filled:
            cv2.fillPoly(img, [pts], col, aa)
        else:
            cv2.polylines(img, [pts], True, col, thick, aa)
    elif kind < 0.85:
        dx, dy = np.cos(a) * r * 1.5, np.sin(a) * r * 1.5
        cv2.line(img, (int(cx - dx), int(cy - dy)), (int(cx + dx), int(cy + dy)), col, 1 + int(u * max(1.0, r / 5)), aa)
    else:
        cv2.circle(img, (int(cx), int(cy)), max(1, int(r)), col, thick, aa)


def _draw_texts(img: np.ndarray, rng: np.random.Generator, palette: np.ndarray, tpu: float, m: int) -> None:
    """``m`` random strings at several sizes (scale 1 ~ 22 texels high ~ 5.5 cm at 400 texels per unit)."""
    h, w = img.shape[:2]
    lens = rng.integers(2, 7, m)
    chars = rng.integers(0, len(_CHARS), int(lens.sum()))
    styles = rng.integers(0, len(_STYLES), m)
    scales = np.exp(rng.uniform(np.log(0.35), np.log(2.2), m)) * tpu / 400.0
    thicks = rng.integers(1, 4, m)
    ox = rng.integers(-20, w, m)
    oy = rng.integers(0, h + 20, m)
    tcol = _colours(rng, palette, m)
    pos = 0
    for i in range(m):
        s = "".join(_CHARS[c] for c in chars[pos : pos + lens[i]])
        pos += lens[i]
        draw_text(img, s, (int(ox[i]), int(oy[i])), float(scales[i]), int(styles[i]), tuple(tcol[i]), int(thicks[i]))


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
