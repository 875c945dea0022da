"""The synthetic room: an exactly posed, textured scene for tests and demos.

The scene is a set of textured planar rectangles ("faces"): the inner walls, floor and ceiling of
a room plus the visible faces of a few boxes.  Each face carries a procedurally generated texture
(:mod:`.texture`) mapped planarly: the texture coordinate of a point ``p`` on the face is
``((p - origin) . u_axis, (p - origin) . v_axis) * texels_per_unit``.  :mod:`.render` casts rays
into it, :mod:`.paths` places cameras in it, :mod:`.sequence` writes rendered sequences to disk.

World frame: x right, y forward (towards the far wall), z up; the room spans
``[-2, 2] x [-1.5, 1.5] x [0, 2.5]`` units (think metres).  Poses are ``cam_from_world`` 4x4
matrices with OpenCV camera axes; pixels follow COLMAP (centre of the top-left pixel = (0.5, 0.5)).
Everything is deterministic for a given seed.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field

import numpy as np

from .texture import _pack_atlas, make_texture

ROOM_MIN = np.array([-2.0, -1.5, 0.0])
ROOM_MAX = np.array([2.0, 1.5, 2.5])
UP = np.array([0.0, 0.0, 1.0])
LIGHT_DIR = np.array([0.35, -0.55, 0.75]) / np.linalg.norm([0.35, -0.55, 0.75])  # towards the light


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

    # -- lazily built helpers ------------------------------------------------------------------
    @property
    def raycaster(self):
        """The Open3D RaycastingScene of the mesh (built on first use)."""
        if self._raycaster is None:
            import open3d as o3d

            rc = o3d.t.geometry.RaycastingScene()
            rc.add_triangles(
                o3d.core.Tensor(np.ascontiguousarray(self.vertices, dtype=np.float32)),
                o3d.core.Tensor(np.ascontiguousarray(self.triangles, dtype=np.uint32)),
            )
            self._raycaster = rc
        return self._raycaster

    @property
    def atlas(self) -> tuple[np.ndarray, np.ndarray]:
        """(atlas image, per-texture (x, y) offset of texel (0, 0) in the atlas)."""
        if self._atlas is None:
            self._atlas = _pack_atlas(self.textures)
        return self._atlas

    def camera_is_valid(self, center: np.ndarray, margin: float = 0.2) -> bool:
        """True when a camera centre lies inside the room, ``margin`` away from walls and boxes."""
        c = np.asarray(center, float)
        if np.any(c < self.bounds[0] + margin) or np.any(c > self.bounds[1] - margin):
            return False
        return not any(bool(b.contains(c, margin)[0]) for b in self.boxes)


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
    for name in (
        "vertices",
        "triangles",
        "tri_face",
        "face_origin",
        "face_u",
        "face_v",
        "face_size",
        "face_normal",
        "face_tex",
        "face_shade",
        "bounds",
    ):
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
    boxes.append(
        b.box(
            (crate_xy[0] + 0.1, crate_xy[1] - 0.05),
            (0.35, 0.3, 0.25 + jit(0.03)),
            z0=crate[2],
            yaw=np.radians(20 + jit(5)),
        )
    )
    boxes.append(b.box((1.15 + jit(0.05), 1.0 + jit(0.05)), (0.45, 0.4, 1.35 + jit(0.05)), yaw=np.radians(jit(4))))
    boxes.append(
        b.box((0.15 + jit(0.05), 0.35 + jit(0.05)), (0.5, 0.45, 0.42 + jit(0.04)), yaw=np.radians(32 + jit(5)))
    )
    # a panel on the far wall: its back face lies on the wall and is skipped
    boxes.append(b.box((0.1 + jit(0.05), y1 - 0.03), (1.1, 0.06, 0.7), z0=1.25 + jit(0.05), skip=("bottom", "+y")))
    return b.build((ROOM_MIN, ROOM_MAX), boxes, seed)
