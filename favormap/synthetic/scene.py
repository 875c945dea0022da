"""A synthetic, exactly posed, textured room rendered by CPU ray casting (Open3D).

The scene is a set of textured planar rectangles ("faces"): the inner walls, floor and ceiling of
a room plus the visible faces of a few boxes.  Each face carries a procedurally generated texture
mapped planarly: the texture coordinate of a point ``p`` on the face is
``((p - origin) . u_axis, (p - origin) . v_axis) * texels_per_unit``.  Rendering casts one ray per
(super-sampled) pixel centre with :class:`open3d.t.geometry.RaycastingScene`, looks up the face of
the hit triangle, samples its texture bilinearly and applies a fixed Lambertian-style shade.

World frame: x right, y forward (towards the far wall), z up; the room spans
``[-2, 2] x [-1.5, 1.5] x [0, 2.5]`` units (think metres).  Poses are ``cam_from_world`` 4x4
matrices with OpenCV camera axes; pixels follow COLMAP (centre of the top-left pixel = (0.5, 0.5)).
Everything is deterministic for a given seed.
"""

from __future__ import annotations

import dataclasses
import functools
import string
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .. import geometry
from ..io.types import Camera, Frame, Sequence

ROOM_MIN = np.array([-2.0, -1.5, 0.0])
ROOM_MAX = np.array([2.0, 1.5, 2.5])
UP = np.array([0.0, 0.0, 1.0])
LIGHT_DIR = np.array([0.35, -0.55, 0.75]) / np.linalg.norm([0.35, -0.55, 0.75])  # towards the light

_ATLAS_WIDTH = 4096
_ATLAS_PAD = 2


@dataclass
class Box:
    """An upright box (rotated by ``yaw`` radians about +z), used to keep cameras out of objects."""

    center: np.ndarray  # (3,)
    half: np.ndarray  # (3,) half extents along the box's own axes
    yaw: float = 0.0

    def axes(self) -> np.ndarray:
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # rows: box x, y, z in world

    def contains(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        local = (np.atleast_2d(points) - self.center) @ self.axes().T
        return np.all(np.abs(local) <= self.half + margin, axis=1)


@dataclass
class Scene:
    """Triangle mesh + per-face planar texture mapping + textures.

    Per face ``f``: ``face_origin[f]`` (3D corner where the texture coordinate is (0, 0)),
    ``face_u[f]``/``face_v[f]`` (unit in-plane axes: texture columns/rows grow along them),
    ``face_size[f]`` (extent along u, v in units), ``face_normal[f]`` (unit, pointing to the side
    the face is seen from), ``face_tex[f]`` (index into ``textures``) and ``face_shade[f]``.
    ``tri_face[t]`` is the face of triangle ``t``.  Textures are RGB uint8 with
    ``texels_per_unit`` texels per unit; texel ``(col, row)`` covers ``[col, col+1) x [row, row+1)``
    in texture coordinates.
    """

    vertices: np.ndarray  # (V,3) float32
    triangles: np.ndarray  # (T,3) uint32
    tri_face: np.ndarray  # (T,) int64
    face_origin: np.ndarray  # (F,3)
    face_u: np.ndarray  # (F,3)
    face_v: np.ndarray  # (F,3)
    face_size: np.ndarray  # (F,2)
    face_normal: np.ndarray  # (F,3)
    face_tex: np.ndarray  # (F,) int64
    face_shade: np.ndarray  # (F,) float32
    textures: list  # list of (h,w,3) uint8 RGB
    texels_per_unit: float
    bounds: np.ndarray  # (2,3) room interior min / max
    boxes: list = field(default_factory=list)  # list[Box]
    seed: int = 0
    _atlas: tuple | None = field(default=None, init=False, repr=False, compare=False)
    _raycaster: object = field(default=None, init=False, repr=False, compare=False)

    @property
    def num_faces(self) -> int:
        return len(self.face_origin)

    # -- lazily built helpers ------------------------------------------------------------------
    @property
    def raycaster(self):
        """The Open3D RaycastingScene of the mesh (built on first use)."""
        if self._raycaster is None:
            import open3d as o3d

            rc = o3d.t.geometry.RaycastingScene()
            rc.add_triangles(o3d.core.Tensor(np.ascontiguousarray(self.vertices, dtype=np.float32)),
                             o3d.core.Tensor(np.ascontiguousarray(self.triangles, dtype=np.uint32)))
            self._raycaster = rc
        return self._raycaster

    @property
    def atlas(self) -> tuple[np.ndarray, np.ndarray]:
        """(atlas image, per-texture (x, y) offset of texel (0, 0) in the atlas)."""
        if self._atlas is None:
            self._atlas = _pack_atlas(self.textures)
        return self._atlas

    def to_open3d(self):
        """A legacy ``open3d.geometry.TriangleMesh`` (untextured, per-face grey shade) for viewing."""
        import open3d as o3d

        verts = self.vertices[self.triangles.reshape(-1)].astype(np.float64)
        tris = np.arange(len(verts)).reshape(-1, 3)
        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(tris))
        shade = np.repeat(self.face_shade[self.tri_face], 3)
        mesh.vertex_colors = o3d.utility.Vector3dVector(np.repeat(shade[:, None], 3, axis=1).astype(np.float64))
        return mesh

    def camera_is_valid(self, center: np.ndarray, margin: float = 0.2) -> bool:
        """True when a camera centre lies inside the room, ``margin`` away from walls and boxes."""
        c = np.asarray(center, float)
        if np.any(c < self.bounds[0] + margin) or np.any(c > self.bounds[1] - margin):
            return False
        return not any(bool(b.contains(c, margin)[0]) for b in self.boxes)


# ---------------------------------------------------------------------------------------------
# textures
# ---------------------------------------------------------------------------------------------
_FONTS = [cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX,
          cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_PLAIN, cv2.FONT_HERSHEY_SCRIPT_SIMPLEX]
_CHARS = string.ascii_letters + string.digits + "#%&@?+"


def _smooth_noise(h: int, w: int, rng: np.random.Generator, base, amplitude: float, finest: float = 2.5,
                  decay: float = 0.72) -> np.ndarray:
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
    return cv2.warpAffine(small, A, (w, h), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REFLECT)


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
            cv2.line(img, (int(cx - dx), int(cy - dy)), (int(cx + dx), int(cy + dy)), col,
                     1 + int(u_all[i] * max(1.0, r / 5)), aa)
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
        s = "".join(_CHARS[c] for c in chars[pos:pos + lens[i]])
        pos += lens[i]
        cv2.putText(img, s, (int(ox[i]), int(oy[i])), _FONTS[int(fonts[i])], float(scales[i]), tuple(tcol[i]),
                    int(thicks[i]), aa)
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
        atlas[y:y + th + 2 * p, x:x + tw + 2 * p] = cv2.copyMakeBorder(textures[i], p, p, p, p, cv2.BORDER_REPLICATE)
        offsets[i] = (x + p, y + p)
    return atlas, offsets


# ---------------------------------------------------------------------------------------------
# scene construction
# ---------------------------------------------------------------------------------------------
class _Builder:
    def __init__(self, rng: np.random.Generator, texels_per_unit: float):
        self.rng = rng
        self.tpu = float(texels_per_unit)
        self.faces = []  # (origin, u, v, size_u, size_v, normal)

    def face(self, center, normal, v_dir, size_u, size_v):
        """A rectangle centred at ``center`` seen from the ``normal`` side; texture rows grow along
        ``v_dir`` and columns along ``u = normal x v`` (reads un-mirrored from the front)."""
        n = np.asarray(normal, float) / np.linalg.norm(normal)
        v = np.asarray(v_dir, float)
        v = v - n * (v @ n)
        v /= np.linalg.norm(v)
        u = np.cross(n, v)
        origin = np.asarray(center, float) - 0.5 * size_u * u - 0.5 * size_v * v
        self.faces.append((origin, u, v, float(size_u), float(size_v), n))

    def box(self, center_xy, size, z0=0.0, yaw=0.0, skip=("bottom",)) -> Box:
        sx, sy, sz = size
        c = np.array([center_xy[0], center_xy[1], z0 + sz / 2])
        b = Box(c, np.array([sx, sy, sz]) / 2, yaw)
        ax, ay, az = b.axes()
        down = -UP
        sides = {
            "+x": (c + ax * sx / 2, ax, down, sy, sz),
            "-x": (c - ax * sx / 2, -ax, down, sy, sz),
            "+y": (c + ay * sy / 2, ay, down, sx, sz),
            "-y": (c - ay * sy / 2, -ay, down, sx, sz),
            "top": (c + az * sz / 2, az, ay, sx, sy),
            "bottom": (c - az * sz / 2, -az, ay, sx, sy),
        }
        for name, (fc, n, vd, su, sv) in sides.items():
            if name not in skip:
                self.face(fc, n, vd, su, sv)
        return b

    def build(self, bounds, boxes, seed) -> Scene:
        F = len(self.faces)
        origin = np.array([f[0] for f in self.faces])
        u = np.array([f[1] for f in self.faces])
        v = np.array([f[2] for f in self.faces])
        size = np.array([[f[3], f[4]] for f in self.faces])
        normal = np.array([f[5] for f in self.faces])
        verts = np.zeros((F, 4, 3))
        verts[:, 0] = origin
        verts[:, 1] = origin + size[:, :1] * u
        verts[:, 2] = origin + size[:, :1] * u + size[:, 1:] * v
        verts[:, 3] = origin + size[:, 1:] * v
        base = 4 * np.arange(F)[:, None]
        tris = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]], axis=0)
        tri_face = np.concatenate([np.arange(F), np.arange(F)])
        textures = []
        for f in range(F):
            tw = int(np.ceil(size[f, 0] * self.tpu)) + 1
            th = int(np.ceil(size[f, 1] * self.tpu)) + 1
            textures.append(make_texture(tw, th, self.rng, self.tpu))
        shade = (0.5 + 0.5 * np.clip(normal @ LIGHT_DIR, 0, 1)).astype(np.float32)
        return Scene(
            vertices=verts.reshape(-1, 3).astype(np.float32),
            triangles=tris.astype(np.uint32),
            tri_face=tri_face.astype(np.int64),
            face_origin=origin,
            face_u=u,
            face_v=v,
            face_size=size,
            face_normal=normal,
            face_tex=np.arange(F, dtype=np.int64),
            face_shade=shade,
            textures=textures,
            texels_per_unit=self.tpu,
            bounds=np.stack([bounds[0], bounds[1]]).astype(float),
            boxes=boxes,
            seed=seed,
        )


def make_room(seed: int = 0, texels_per_unit: float = 400.0) -> Scene:
    """A 4 x 3 x 2.5 room (walls, floor, ceiling, all facing inwards) with a few textured boxes
    standing in its far half (y > 0): a large crate with a small rotated box on top, a tall
    column, a rotated box in the middle and a flat panel hanging on the far wall.

    Rooms are cached per (seed, texels_per_unit): the returned Scene shares its (read-only)
    arrays and textures with the cache."""
    base = _cached_room(int(seed), float(texels_per_unit))
    scene = dataclasses.replace(base, textures=list(base.textures), boxes=list(base.boxes))
    scene._atlas = base._atlas
    return scene


@functools.lru_cache(maxsize=2)
def _cached_room(seed: int, texels_per_unit: float) -> Scene:
    scene = _build_room(seed, texels_per_unit)
    for name in ("vertices", "triangles", "tri_face", "face_origin", "face_u", "face_v", "face_size", "face_normal",
                 "face_tex", "face_shade", "bounds"):
        getattr(scene, name).flags.writeable = False
    for t in scene.textures:
        t.flags.writeable = False
    scene.atlas[0].flags.writeable = False
    scene.atlas[1].flags.writeable = False
    return scene


def _build_room(seed: int, texels_per_unit: float) -> Scene:
    rng = np.random.default_rng(seed)
    jit = lambda s: rng.uniform(-s, s)  # noqa: E731  small per-seed layout jitter
    b = _Builder(rng, texels_per_unit)
    (x0, y0, z0), (x1, y1, z1) = ROOM_MIN, ROOM_MAX
    cx, cy, cz = (ROOM_MIN + ROOM_MAX) / 2
    X, Y, Z = ROOM_MAX - ROOM_MIN
    down = -UP
    # walls (normals point into the room), floor, ceiling
    b.face((cx, y1, cz), (0, -1, 0), down, X, Z)  # far wall
    b.face((cx, y0, cz), (0, 1, 0), down, X, Z)  # near wall
    b.face((x0, cy, cz), (1, 0, 0), down, Y, Z)  # left wall
    b.face((x1, cy, cz), (-1, 0, 0), down, Y, Z)  # right wall
    b.face((cx, cy, z0), (0, 0, 1), (0, -1, 0), X, Y)  # floor
    b.face((cx, cy, z1), (0, 0, -1), (0, 1, 0), X, Y)  # ceiling

    boxes = []
    crate = (0.85 + jit(0.05), 0.65 + jit(0.05), 0.7 + jit(0.05))
    crate_xy = (-1.0 + jit(0.05), 0.85 + jit(0.05))
    boxes.append(b.box(crate_xy, crate, yaw=np.radians(jit(3))))
    boxes.append(b.box((crate_xy[0] + 0.1, crate_xy[1] - 0.05), (0.35, 0.3, 0.25 + jit(0.03)), z0=crate[2],
                       yaw=np.radians(20 + jit(5))))
    boxes.append(b.box((1.15 + jit(0.05), 1.0 + jit(0.05)), (0.45, 0.4, 1.35 + jit(0.05)), yaw=np.radians(jit(4))))
    boxes.append(b.box((0.15 + jit(0.05), 0.35 + jit(0.05)), (0.5, 0.45, 0.42 + jit(0.04)),
                       yaw=np.radians(32 + jit(5))))
    # a panel on the far wall: its back face lies on the wall and is skipped
    boxes.append(b.box((0.1 + jit(0.05), y1 - 0.03), (1.1, 0.06, 0.7), z0=1.25 + jit(0.05), skip=("bottom", "+y")))
    return b.build((ROOM_MIN, ROOM_MAX), boxes, seed)


# ---------------------------------------------------------------------------------------------
# rendering
# ---------------------------------------------------------------------------------------------
def _pixel_rays(camera: Camera, cam_from_world: np.ndarray, ss: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """World rays through the centres of an ``ss`` times super-sampled pixel grid.  Directions
    have unit z in the camera frame, so the ray parameter of a hit is its z-depth."""
    if not camera.is_pinhole:
        raise ValueError(f"render needs a pinhole camera, got {camera.model}")
    fx, fy = camera.focal
    cx, cy = camera.principal_point
    W, H = camera.width * ss, camera.height * ss
    xs = (((np.arange(W, dtype=np.float64) + 0.5) / ss - cx) / fx).astype(np.float32)
    ys = (((np.arange(H, dtype=np.float64) + 0.5) / ss - cy) / fy).astype(np.float32)
    T = np.asarray(cam_from_world, float)
    R = T[:3, :3].astype(np.float32)
    center = geometry.camera_centers(T)
    rays = np.empty((H, W, 2, 3), np.float32)
    rays[:, :, 0] = center.astype(np.float32)
    # d_world = R^T d_cam = x * R[0] + y * R[1] + R[2]
    np.add((xs[:, None] * R[0] + R[2])[None], (ys[:, None] * R[1])[:, None, :], out=rays[:, :, 1])
    return rays.reshape(-1, 6), center


def _cast(scene: Scene, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    ans = scene.raycaster.cast_rays(o3d.core.Tensor(rays))
    t = ans["t_hit"].numpy()
    prim = ans["primitive_ids"].numpy().astype(np.int64)
    hit = np.isfinite(t)
    face = np.full(len(t), -1, np.int64)
    face[hit] = scene.tri_face[prim[hit]]
    return t, face


def render_depth(scene: Scene, camera: Camera, cam_from_world: np.ndarray) -> np.ndarray:
    """z-depth (along the optical axis) at each pixel centre, float32 HxW, inf where nothing is hit."""
    rays, _ = _pixel_rays(camera, cam_from_world, 1)
    t, _ = _cast(scene, rays)
    return t.reshape(camera.height, camera.width).astype(np.float32)


def render(scene: Scene, camera: Camera, cam_from_world: np.ndarray, ss: int = 2,
           with_depth: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Render ``scene`` seen by a pinhole ``camera`` at ``cam_from_world``.

    Returns (rgb uint8 HxWx3, depth float32 HxW): the colour is averaged over ``ss x ss`` samples
    per pixel (anti-aliasing), the depth is the z-depth at the pixel centre (COLMAP convention),
    inf where no surface is hit; None when ``with_depth`` is False.
    """
    ss = max(1, int(ss))
    W, H = camera.width * ss, camera.height * ss
    rays, center = _pixel_rays(camera, cam_from_world, ss)
    t, face = _cast(scene, rays)
    hit = face >= 0
    atlas, offsets = scene.atlas

    f = np.where(hit, face, 0)
    th = np.where(hit, t, 0).astype(np.float32)[:, None]
    p = center.astype(np.float32)[None, :] + th * rays[:, 3:]
    dp = p - scene.face_origin.astype(np.float32)[f]
    tpu = np.float32(scene.texels_per_unit)
    s_coord = np.einsum("ij,ij->i", dp, scene.face_u.astype(np.float32)[f]) * tpu
    t_coord = np.einsum("ij,ij->i", dp, scene.face_v.astype(np.float32)[f]) * tpu
    tex = scene.face_tex[f]
    tw = np.array([x.shape[1] for x in scene.textures], np.float32)[tex]
    tht = np.array([x.shape[0] for x in scene.textures], np.float32)[tex]
    # texel (c, r) covers [c, c+1) x [r, r+1); cv2.remap samples texel centres at integers
    mapx = offsets[tex, 0] + np.clip(s_coord - 0.5, -0.5, tw - 0.5)
    mapy = offsets[tex, 1] + np.clip(t_coord - 0.5, -0.5, tht - 0.5)
    mapx[~hit] = -10.0
    mapy[~hit] = -10.0
    img = cv2.remap(atlas, mapx.reshape(H, W), mapy.reshape(H, W), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))
    shade = np.where(hit, scene.face_shade[f], 0).astype(np.float32)
    img = img.astype(np.float32) * shade.reshape(H, W, 1)
    if ss > 1:
        img = cv2.resize(img, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    rgb = np.clip(img + 0.5, 0, 255).astype(np.uint8)

    depth = None
    if with_depth:
        if ss == 1:
            depth = t.reshape(H, W).astype(np.float32)
        else:
            depth = render_depth(scene, camera, cam_from_world)
    return rgb, depth


def surface_distance(scene: Scene, points: np.ndarray) -> np.ndarray:
    """Unsigned distance from each (N,3) point to the scene surface (Open3D compute_distance)."""
    import open3d as o3d

    pts = np.ascontiguousarray(np.atleast_2d(points), dtype=np.float32)
    return scene.raycaster.compute_distance(o3d.core.Tensor(pts)).numpy().astype(np.float64)


def backproject(camera: Camera, cam_from_world: np.ndarray, pixels: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """World points of (N,2) pixel coordinates (COLMAP convention) with z-depths (N,)."""
    pixels = np.atleast_2d(np.asarray(pixels, float))
    fx, fy = camera.focal
    cx, cy = camera.principal_point
    z = np.asarray(depth, float).reshape(-1)
    Xc = np.stack([(pixels[:, 0] - cx) / fx * z, (pixels[:, 1] - cy) / fy * z, z], axis=1)
    return geometry.transform_points(geometry.inverse(cam_from_world), Xc)


def project(camera: Camera, cam_from_world: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,2) pixel coordinates (COLMAP convention) and (N,) z-depths of world points."""
    Xc = geometry.transform_points(np.asarray(cam_from_world, float), np.atleast_2d(points))
    fx, fy = camera.focal
    cx, cy = camera.principal_point
    z = Xc[:, 2]
    return np.stack([fx * Xc[:, 0] / z + cx, fy * Xc[:, 1] / z + cy], axis=1), z


# ---------------------------------------------------------------------------------------------
# cameras and paths
# ---------------------------------------------------------------------------------------------
def make_camera(width: int = 640, height: int = 480, fov_deg: float = 60.0) -> Camera:
    """A PINHOLE camera with horizontal field of view ``fov_deg`` and a centred principal point."""
    f = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    return Camera("PINHOLE", int(width), int(height), [f, f, width / 2.0, height / 2.0])


def _smooth_jitter(rng: np.random.Generator, dims: int, amp: float):
    """A smooth random function of arc length s (sum of a few sinusoids), returns s -> (len(s), dims)."""
    k = 3
    lam = rng.uniform(0.6, 2.5, (k, dims))
    ph = rng.uniform(0, 2 * np.pi, (k, dims))
    a = rng.uniform(0.3, 1.0, (k, dims))
    a *= amp / a.sum(axis=0)

    def f(s):
        s = np.asarray(s, float)[:, None, None]
        return np.sum(a * np.sin(2 * np.pi * s / lam + ph), axis=1)

    return f


def _loop(kind: str, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres and look-at targets of a closed loop, parameterised by phi (2 pi periodic)."""
    if kind == "orbit":
        # arc around the box cluster: out along an outer lane, back along an inner, lower lane
        c = np.array([0.0, 0.55, 0.8])
        alpha = np.radians(50) * np.sin(phi)
        r = 1.68 + 0.1 * np.cos(phi)
        eye = np.stack([c[0] + r * np.sin(alpha), c[1] - r * np.cos(alpha), 1.4 + 0.18 * np.cos(phi)], axis=1)
        target = np.tile(c, (len(phi), 1))
        target[:, 0] += 0.25 * np.sin(alpha)
        return eye, target
    if kind == "walk":
        # lateral walk facing the far wall, with a little forward/backward and up/down motion
        x = 1.25 * np.sin(phi)
        eye = np.stack([x, -0.85 + 0.2 * np.cos(phi), 1.5 + 0.1 * np.sin(2 * phi)], axis=1)
        target = np.stack([0.6 * x + 0.2 * np.cos(phi), np.full_like(x, 1.5), 0.95 + 0.1 * np.cos(phi)], axis=1)
        return eye, target
    raise ValueError(f"unknown camera path kind {kind!r} (use 'orbit' or 'walk')")


def _roll(cam_from_world: np.ndarray, angle_rad: float) -> np.ndarray:
    Rz = np.eye(4)
    Rz[:3, :3] = geometry.rotation_about([0.0, 0.0, 1.0], angle_rad)
    return Rz @ cam_from_world


def camera_path(n: int, kind: str = "orbit", seed: int = 0, step: float = 0.07) -> list[np.ndarray]:
    """``n`` cam_from_world poses along a smooth closed path inside the room made by
    :func:`make_room`, ``step`` units apart (uniform in arc length), looking at the room content
    with a small smooth look-at and roll jitter.  Consecutive frames overlap strongly (a few
    degrees of rotation per frame), so features can be followed through many frames.
    ``kind``: "orbit" (an arc ~1.7 units around the boxes) or "walk" (a lateral walk ~2.3 units
    from the far wall)."""
    rng = np.random.default_rng([int(seed), 7])
    phi0 = -np.pi / 2 + rng.uniform(-0.3, 0.3)
    dense = np.linspace(0, 2 * np.pi, 4001)
    eye, _ = _loop(kind, phi0 + dense)
    seg = np.linalg.norm(np.diff(eye, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    loop_len = cum[-1]
    s = np.arange(n) * float(step)
    phi = phi0 + 2 * np.pi * np.floor(s / loop_len) + np.interp(s % loop_len, cum, dense)
    eye, target = _loop(kind, phi)
    target = target + _smooth_jitter(rng, 3, 0.06)(s)
    roll = _smooth_jitter(rng, 1, np.radians(2.5))(s)[:, 0]
    return [_roll(geometry.look_at(e, t, up=UP), r) for e, t, r in zip(eye, target, roll)]


def _slerp_R(R0: np.ndarray, R1: np.ndarray, w: float) -> np.ndarray:
    q0 = geometry.rotmat_to_quat(R0)
    q1 = geometry.rotmat_to_quat(R1)
    if q0 @ q1 < 0:
        q1 = -q1
    dot = float(np.clip(q0 @ q1, -1, 1))
    th = np.arccos(dot)
    if th < 1e-8:
        q = q0
    else:
        q = (np.sin((1 - w) * th) * q0 + np.sin(w * th) * q1) / np.sin(th)
    return geometry.quat_to_rotmat(q)


def random_views_near(poses, n: int, seed: int = 0, max_trans: float = 0.1, max_rot_deg: float = 5.0,
                      scene: Scene | None = None) -> list[np.ndarray]:
    """``n`` held-out poses near a path: each interpolates two consecutive ``poses`` at a random
    fraction (centre linearly, rotation by slerp), then moves by up to ``max_trans`` units and
    rotates by up to ``max_rot_deg`` degrees in random directions.  With ``scene``, poses whose
    centre is not safely inside the room (see :meth:`Scene.camera_is_valid`) are redrawn."""
    poses = [np.asarray(p, float) for p in poses]
    if not poses:
        raise ValueError("random_views_near needs at least one pose")
    rng = np.random.default_rng([int(seed), 11])
    out = []
    tries = 0
    while len(out) < n:
        tries += 1
        if tries > 1000 * max(1, n):
            raise RuntimeError("could not place valid views near the given poses")
        i = int(rng.integers(0, max(1, len(poses) - 1)))
        j = min(i + 1, len(poses) - 1)
        w = float(rng.uniform(0, 1))
        A, B = geometry.inverse(poses[i]), geometry.inverse(poses[j])
        wfc = np.eye(4)
        wfc[:3, :3] = _slerp_R(A[:3, :3], B[:3, :3], w)
        wfc[:3, 3] = (1 - w) * A[:3, 3] + w * B[:3, 3]
        T = geometry.perturb_pose(geometry.inverse(wfc), float(rng.uniform(0, max_trans)),
                                  float(rng.uniform(0, max_rot_deg)), rng)
        if scene is not None and not scene.camera_is_valid(geometry.camera_centers(T)):
            continue
        out.append(T)
    return out


# ---------------------------------------------------------------------------------------------
# sequences on disk
# ---------------------------------------------------------------------------------------------
def write_sequence(root, n_frames: int = 30, width: int = 640, height: int = 480, fov_deg: float = 60.0,
                   seed: int = 0, path: str = "orbit", depth: bool = False, ss: int = 2,
                   poses=None, scene: Scene | None = None, step: float = 0.07) -> Sequence:
    """Render a posed sequence of the room into ``root`` in the plain favormap layout:
    ``root/images/000000.png ...`` and ``root/sequence.json`` (one PINHOLE camera, id 0); with
    ``depth``, also ``root/depth/000000.npy ...`` (float32 z-depth, inf where nothing is hit).

    ``poses`` overrides the path (e.g. query views from :func:`random_views_near`); ``scene``
    overrides ``make_room(seed)``.  Returns the Sequence (``extra["synthetic"]`` notes the
    settings; ``extra["depth"]`` lists the depth files when written)."""
    from ..io.readers import favormap_layout

    root = Path(root)
    scene = scene if scene is not None else make_room(seed)
    custom = poses is not None
    if not custom:
        poses = camera_path(n_frames, kind=path, seed=seed, step=step)
    poses = [np.asarray(p, float) for p in poses]
    camera = make_camera(width, height, fov_deg)
    (root / "images").mkdir(parents=True, exist_ok=True)
    if depth:
        (root / "depth").mkdir(parents=True, exist_ok=True)
    frames, depth_files = [], []
    for i, T in enumerate(poses):
        rgb, d = render(scene, camera, T, ss=ss, with_depth=depth)
        name = f"images/{i:06d}.png"
        if not cv2.imwrite(str(root / name), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
            raise OSError(f"cannot write {root / name}")
        if depth:
            dname = f"depth/{i:06d}.npy"
            np.save(root / dname, d)
            depth_files.append(dname)
        frames.append(Frame(name, root / name, 0, T))
    extra = {"synthetic": {"scene": "room", "seed": int(seed), "path": "custom" if custom else path,
                           "fov_deg": float(fov_deg), "ss": int(ss)}}
    if depth:
        extra["depth"] = depth_files
    seq = Sequence(root, favormap_layout.NAME, {0: camera}, frames, extra)
    favormap_layout.write(seq, root)
    return seq
