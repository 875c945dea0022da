"""Stage boundary of the readers: a posed image sequence."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# Camera models favormap accepts, with pycolmap's parameter order.
SUPPORTED_MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "SIMPLE_RADIAL_FISHEYE": ("f", "cx", "cy", "k"),
    "RADIAL_FISHEYE": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
    "FOV": ("fx", "fy", "cx", "cy", "omega"),
}
# Wide-angle models: their images are undistorted to a pinhole working camera of its own focal length
# (see io.images.working_camera), not to the camera's own focal length as the perspective models are.
FISHEYE_MODELS = ("SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "OPENCV_FISHEYE", "FOV")
# models with a single focal length (f, cx, cy, ...)
_ONE_FOCAL = ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE")


@dataclass
class Camera:
    """A camera in COLMAP's model/parameter convention (pixel centre of top-left pixel = 0.5).

    ``working_fov``: the horizontal field of view (degrees, in (0, 180)) of the pinhole working camera
    its images are undistorted to; None: the default rule of :func:`io.images.working_camera`. Pinhole
    cameras ignore it."""

    model: str
    width: int
    height: int
    params: np.ndarray
    working_fov: float | None = None

    def __post_init__(self):
        from ..errors import InputError

        self.params = np.asarray(self.params, dtype=np.float64)
        if self.model not in SUPPORTED_MODELS:
            raise InputError(f"unsupported camera model {self.model!r} (supported: {', '.join(SUPPORTED_MODELS)})")
        if len(self.params) != len(SUPPORTED_MODELS[self.model]):
            raise InputError(
                f"camera model {self.model} needs {len(SUPPORTED_MODELS[self.model])} parameters, got "
                f"{len(self.params)}"
            )
        if self.width <= 0 or self.height <= 0 or not np.all(np.isfinite(self.params)):
            raise InputError(f"invalid camera: {self.width}x{self.height} {self.params.tolist()}")
        if self.working_fov is not None:
            self.working_fov = float(self.working_fov)
            if not 0 < self.working_fov < 180:
                raise InputError(f"working field of view must be in (0, 180) degrees, got {self.working_fov:g}")

    # -- intrinsics ---------------------------------------------------------------------------
    @property
    def focal(self) -> tuple[float, float]:
        p = self.params
        if self.model in _ONE_FOCAL:
            return float(p[0]), float(p[0])
        return float(p[0]), float(p[1])

    @property
    def principal_point(self) -> tuple[float, float]:
        p = self.params
        if self.model in _ONE_FOCAL:
            return float(p[1]), float(p[2])
        return float(p[2]), float(p[3])

    @property
    def K(self) -> np.ndarray:
        fx, fy = self.focal
        cx, cy = self.principal_point
        return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])

    @property
    def is_pinhole(self) -> bool:
        return self.model in ("SIMPLE_PINHOLE", "PINHOLE")

    @property
    def is_fisheye(self) -> bool:
        return self.model in FISHEYE_MODELS

    @property
    def has_distortion(self) -> bool:
        """Whether the camera's pixels differ from those of the pinhole with its focal length and
        principal point (FOV's omega = 0 and fisheye models are never distortion-free)."""
        if self.is_fisheye:
            return True
        return not self.is_pinhole and bool(np.any(self.opencv_distortion() != 0))

    def opencv_distortion(self) -> np.ndarray:
        """Distortion coefficients in OpenCV's order: (k1, k2, p1, p2[, k3, k4, k5, k6]) for the
        perspective models; for the fisheye models ``cv2.fisheye``'s (k1, k2, k3, k4). FOV has none."""
        from ..errors import InputError

        p = self.params
        if self.model == "FOV":
            raise InputError("the FOV camera model has no OpenCV distortion coefficients")
        if self.model == "SIMPLE_RADIAL_FISHEYE":
            return np.array([p[3], 0, 0, 0])
        if self.model == "RADIAL_FISHEYE":
            return np.array([p[3], p[4], 0, 0])
        if self.model == "OPENCV_FISHEYE":
            return p[4:8].copy()
        if self.is_pinhole:
            return np.zeros(4)
        if self.model == "SIMPLE_RADIAL":
            return np.array([p[3], 0, 0, 0])
        if self.model == "RADIAL":
            return np.array([p[3], p[4], 0, 0])
        if self.model == "OPENCV":
            return p[4:8].copy()
        return np.array([p[4], p[5], p[6], p[7], p[8], p[9], p[10], p[11]])

    def pinhole(self) -> Camera:
        """The undistorted pinhole camera with the same focal length and principal point."""
        fx, fy = self.focal
        cx, cy = self.principal_point
        return Camera("PINHOLE", self.width, self.height, [fx, fy, cx, cy])

    def scaled(self, new_width: int, new_height: int) -> Camera:
        """The same camera for an image resized to ``new_width`` x ``new_height``."""
        sx, sy = new_width / self.width, new_height / self.height
        p = self.params.copy()
        if self.model in _ONE_FOCAL:
            p[0] *= (sx + sy) / 2
            p[1] *= sx
            p[2] *= sy
        else:
            p[0] *= sx
            p[1] *= sy
            p[2] *= sx
            p[3] *= sy
        return Camera(self.model, new_width, new_height, p, self.working_fov)

    def to_pycolmap(self):
        import pycolmap

        return pycolmap.Camera(
            model=self.model, width=int(self.width), height=int(self.height), params=self.params.tolist()
        )

    def with_working_fov(self, fov_deg: float | None) -> Camera:
        """The same camera with another working field of view (None: the default rule)."""
        return Camera(self.model, self.width, self.height, self.params.copy(), fov_deg)

    def to_dict(self) -> dict:
        d = {
            "model": self.model,
            "width": int(self.width),
            "height": int(self.height),
            "params": self.params.tolist(),
        }
        if self.working_fov is not None:
            d["working_fov"] = self.working_fov
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Camera:
        fov = d.get("working_fov")
        return cls(str(d["model"]), int(d["width"]), int(d["height"]), d["params"], None if fov is None else float(fov))


@dataclass
class Frame:
    """One posed image of a sequence."""

    name: str  # unique, relative to the sequence root
    image_path: Path
    camera_id: int
    cam_from_world: np.ndarray  # 4x4, OpenCV axes

    def __post_init__(self):
        self.cam_from_world = np.asarray(self.cam_from_world, dtype=np.float64)


@dataclass
class Sequence:
    """A posed image sequence: what every reader returns."""

    root: Path
    format: str
    cameras: dict[int, Camera]
    frames: list[Frame]
    extra: dict = field(default_factory=dict)  # reader-specific notes (e.g. train/test split)

    def __len__(self) -> int:
        return len(self.frames)

    def subset(self, indices) -> Sequence:
        frames = [self.frames[i] for i in indices]
        used = {f.camera_id for f in frames}
        return Sequence(
            self.root, self.format, {k: v for k, v in self.cameras.items() if k in used}, frames, dict(self.extra)
        )
