"""The shared base of the rerun recordings: one dedicated ``rr.RecordingStream`` per command
(never the global one, so favormap is safe to embed in programs that use rerun themselves), its
sinks, the map view every recording can show, and the drawing helpers.

A failure while logging never breaks the command: it is reported once on stderr and logging stops
(set ``FAVORMAP_RERUN_STRICT=1`` to raise instead, as the tests do).
"""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path

import cv2
import numpy as np
import rerun as rr

from .. import geometry
from ..colors import viridis
from ..errors import InputError
from . import DEFAULT_PORT
from .blueprint import blueprint_for
from .viewer import _check_url, spawn_viewer

# preview sizes (longest side, px) and JPEG quality of the logged images
FRAME_IMAGE_SIDE = 320
QUERY_IMAGE_SIDE = 640
JPEG_QUALITY = 80
MAX_FRUSTUMS = 300  # static camera-path frustums drawn at most (evenly subsampled)

GREY = (150, 150, 150)
INLIER = (40, 220, 80)
OUTLIER = (240, 60, 50)
GUIDED = (200, 90, 255)  # inliers that only the guided step found (by projection)
ALIGNED = (255, 80, 200)  # inlier keypoints moved to the mapping images (LocalizeConfig.align)
PRIOR = (255, 160, 0)
GT = (60, 200, 255)
SERIES = {"rendered": (70, 130, 255), "mean": (255, 140, 0), "prior": (150, 150, 150)}


# ---------------------------------------------------------------------------------------------
# small helpers
# ---------------------------------------------------------------------------------------------
def colormap(values, lo: float | None = None, hi: float | None = None) -> np.ndarray:
    """Values -> viridis RGB uint8 (N, 3); ``lo``/``hi`` default to the 2nd/98th percentiles."""
    return viridis(values, lo, hi)[0]


def id_colors(ids) -> np.ndarray:
    """A stable, well-spread colour per integer id (golden-ratio hues), uint8 (N, 3)."""
    h = (np.asarray(ids, np.float64).ravel() * 0.618033988749895) % 1.0
    s, v = 0.75, 0.95
    k = (np.array([5.0, 3.0, 1.0])[None] + h[:, None] * 6.0) % 6.0
    rgb = v - v * s * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
    return np.round(rgb * 255).astype(np.uint8)


def _transform(cam_from_world: np.ndarray) -> rr.Transform3D:
    wfc = geometry.inverse(cam_from_world)
    return rr.Transform3D(translation=wfc[:3, 3], mat3x3=wfc[:3, :3])


def _pinhole(K: np.ndarray, w: int, h: int, depth: float, color=None) -> rr.Pinhole:
    return rr.Pinhole(image_from_camera=K, resolution=[w, h], image_plane_distance=float(depth), color=color)


def _scaled_K(K: np.ndarray, s: float) -> np.ndarray:
    return np.diag([s, s, 1.0]) @ K


def _jpeg(img: np.ndarray, max_side: int) -> tuple[rr.EncodedImage, float, int, int]:
    """RGB uint8 -> (JPEG image downscaled to ``max_side``, scale factor, width, height)."""
    h, w = img.shape[:2]
    s = min(1.0, max_side / max(w, h))
    if s < 1.0:
        w2, h2 = max(1, round(w * s)), max(1, round(h * s))
        img = cv2.resize(img, (w2, h2), interpolation=cv2.INTER_AREA)
        s = w2 / w
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg"), s, img.shape[1], img.shape[0]


def frustum_segments(cam_from_world: np.ndarray, Ks: np.ndarray, sizes: np.ndarray, depth: float) -> np.ndarray:
    """Wireframe frustums as line segments (N*8, 2, 3): 4 rays from the centre + the image rectangle
    at ``depth`` in front of each camera."""
    T = np.asarray(cam_from_world, np.float64).reshape(-1, 4, 4)
    n = len(T)
    if n == 0:
        return np.zeros((0, 2, 3))
    w, h = sizes[:, 0].astype(np.float64), sizes[:, 1].astype(np.float64)
    px = np.stack(
        [
            np.stack([np.zeros(n), np.zeros(n)], 1),
            np.stack([w, np.zeros(n)], 1),
            np.stack([w, h], 1),
            np.stack([np.zeros(n), h], 1),
        ],
        1,
    )  # (n, 4, 2)
    rays = geometry.unproject(np.asarray(Ks)[:, None], px) * depth
    wfc = geometry.inverse(T)
    corners = np.einsum("nij,nkj->nki", wfc[:, :3, :3], rays) + wfc[:, None, :3, 3]
    c = np.repeat(wfc[:, None, :3, 3], 4, axis=1)
    rays_seg = np.stack([c, corners], 2)  # (n, 4, 2, 3)
    rect_seg = np.stack([corners, np.roll(corners, -1, axis=1)], 2)
    return np.concatenate([rays_seg, rect_seg], 1).reshape(-1, 2, 3)


def view_coordinates(cam_from_world: np.ndarray):
    """World axis convention for the 3D view: the world axis closest to the cameras' mean image-up
    direction is 'up' (cameras are mostly held upright)."""
    T = np.asarray(cam_from_world, np.float64).reshape(-1, 4, 4)
    if len(T) == 0:
        return None
    up = -T[:, 1, :3].mean(0)  # camera -y axis in world coordinates
    if np.linalg.norm(up) < 1e-6:
        return None
    k = int(np.argmax(np.abs(up)))
    name = f"RIGHT_HAND_{'XYZ'[k]}_{'UP' if up[k] > 0 else 'DOWN'}"
    return getattr(rr.ViewCoordinates, name)


def frustum_depth(cam_from_world: np.ndarray, depths=None) -> float:
    """Size of the drawn frustums: 1/5 of the typical viewing depth, else 1/20 of the path extent."""
    if depths is not None:
        d = np.asarray(depths, np.float64).ravel()
        d = d[np.isfinite(d) & (d > 0)]
        if len(d):
            return float(0.2 * np.median(d))
    c = geometry.camera_centers(np.asarray(cam_from_world, np.float64).reshape(-1, 4, 4))
    if len(c) < 2:
        return 0.1
    ext = float(np.linalg.norm(np.ptp(c, axis=0)))
    step = float(np.median(np.linalg.norm(np.diff(c, axis=0), axis=1)))
    d = max(0.05 * ext, 2.0 * step)
    return d if d > 0 else 0.1


def markdown_table(rows: list[tuple], header: tuple) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(x) for x in r) + " |" for r in rows]
    return "\n".join(out)


def _guarded(fn):
    @functools.wraps(fn)
    def wrapper(self, *a, **kw):
        if self._failed:
            return None
        try:
            return fn(self, *a, **kw)
        except Exception as e:  # noqa: BLE001 - visualisation must not break the command
            if self.strict:
                raise
            self._failed = True
            print(
                f"favormap: rerun logging failed ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}); "
                "continuing without it",
                file=sys.stderr,
            )
            return None

    return wrapper


class RecordingBase:
    """Sinks, lifecycle, timelines and the map view; the per-command logs are mixins over it
    (:mod:`.build_log`, :mod:`.localize_log`, :mod:`.ops_log`), put together in :mod:`.recording`."""

    def __init__(
        self,
        app_id: str,
        kind: str = "view",
        *,
        spawn: bool = False,
        save=None,
        connect: str | None = None,
        map_=None,
        methods: list[str] | None = None,
        port: int = DEFAULT_PORT,
        strict: bool | None = None,
    ):
        self.kind = kind
        self.methods = list(methods or ["rendered"])
        self.strict = (os.environ.get("FAVORMAP_RERUN_STRICT", "") not in ("", "0")) if strict is None else strict
        self._failed = False
        self._closed = False
        self._styled: set[str] = set()
        self._map_positions = None
        self._map_camera = None
        self._map_max_side = 640
        self._depth = None
        self._frame_cams = None
        self._frame_scale = None
        self._frame_T = None
        self._frame_pinholes = []
        self.spawned = bool(spawn)
        self.save_path = Path(save) if save else None
        if self.save_path is not None:
            if self.save_path.is_dir():
                raise InputError(f"--rerun-save {self.save_path} is a directory")
            if not self.save_path.parent.exists():
                raise InputError(f"--rerun-save: folder {self.save_path.parent} does not exist")
        self.rec = rr.RecordingStream(app_id, make_default=False, make_thread_default=False)
        self.blueprint = blueprint_for(kind, self.methods)
        sinks = []
        if self.save_path is not None:
            sinks.append(rr.FileSink(str(self.save_path)))
        if connect:
            _check_url(connect)
            sinks.append(rr.GrpcSink(connect))
        self._viewer = None  # the viewer process this recording started
        if spawn:
            self._viewer = spawn_viewer(port)
            url = f"rerun+http://127.0.0.1:{port}/proxy"
            if url != connect:
                sinks.append(rr.GrpcSink(url))
        self.rec.set_sinks(*sinks, default_blueprint=self.blueprint)
        if map_ is not None:
            self.log_map(map_, voxels=kind not in ("localize", "eval", "query"))

    # -- lifecycle --------------------------------------------------------------------------------
    def close(self) -> bool:
        """Flush everything and close the sinks (finalizes the .rrd file). False when the data could
        not be delivered (e.g. the viewer went away); that is reported, never raised."""
        if self._closed:
            return True
        self._closed = True
        ok = not self._failed
        for step in (lambda: self.rec.flush(timeout_sec=10.0), self.rec.disconnect):  # both, whatever happens
            try:
                step()
            except Exception as e:  # noqa: BLE001 - the command itself succeeded
                if self.strict:
                    raise
                if ok:
                    print(f"favormap: warning: {self._undelivered(e)}", file=sys.stderr)
                ok = False
        return ok

    def _undelivered(self, e: Exception) -> str:
        why = str(e).splitlines()[0] if str(e) else type(e).__name__
        viewer = getattr(self, "_viewer", None)
        if viewer is not None and viewer.poll() is not None:
            return (
                f"the rerun viewer could not start or exited (exit code {viewer.returncode}; {why}); "
                "use --rerun-save FILE.rrd"
            )
        return f"the rerun recording was not fully delivered ({why})"

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _at(self, timeline: str | None = None, value: int | None = None) -> None:
        self.rec.reset_time()
        if timeline is not None:
            self.rec.set_time(timeline, sequence=int(value))

    def _series(self, path: str, name: str, color) -> None:
        if path not in self._styled:
            self._styled.add(path)
            self.rec.log(path, rr.SeriesLines(names=name, colors=[color]), static=True)

    # -- maps (view, merge, prune, and context for localize/eval) ---------------------------------
    @_guarded
    def log_map(self, m, path: str = "world/map", voxels: bool = True, color_by: str = "track_length") -> None:
        """A map (``Map`` or ``MapData``): landmarks (coloured by track length or quality), voxel
        boxes coloured by quality (PSNR), the mapping camera path with frustums, and its summary."""
        from ..io import working_camera

        P = np.asarray(m.positions, np.float64)
        T = np.asarray(m.cam_from_world, np.float64).reshape(-1, 4, 4)
        q = np.asarray(m.quality, np.float64)
        self._at()
        vc = view_coordinates(T)
        if vc is not None and path == "world/map":
            self.rec.log("world", vc, static=True)
        depth_range = getattr(m, "depth_range", None)
        depth = frustum_depth(
            T, None if depth_range is None or len(depth_range) == 0 else np.asarray(depth_range)[:, 0]
        )
        if path == "world/map":
            self._map_positions = P
            self._map_max_side = int(getattr(m, "max_side", 640) or 0)
            self._depth = depth
            ids = np.asarray(getattr(m, "frame_camera_ids", []))
            cams = getattr(m, "cameras", {}) or {}
            self._map_camera = (
                cams.get(int(ids[0])) if len(ids) and int(ids[0]) in cams else next(iter(cams.values()), None)
            )
        vals = q if color_by == "quality" else np.asarray(m.track_length, np.float64)
        self.rec.log(
            f"{path}/landmarks", rr.Points3D(P, colors=colormap(vals), radii=rr.Radius.ui_points(2.0)), static=True
        )
        if voxels and len(P):
            half = np.repeat(np.asarray(m.voxel_size, np.float64)[:, None] / 2, 3, axis=1)
            self.rec.log(
                f"{path}/voxels",
                rr.Boxes3D(centers=P, half_sizes=half, colors=colormap(q), radii=rr.Radius.ui_points(0.5)),
                static=True,
            )
        if len(T):
            cams = getattr(m, "cameras", {}) or {}
            ids = np.asarray(getattr(m, "frame_camera_ids", np.zeros(len(T), int)))
            wcams = {cid: working_camera(c, self._map_max_side or None) for cid, c in cams.items()}
            if wcams:
                fallback = next(iter(wcams.values()))
                wc = [wcams.get(int(i), fallback) for i in ids]
                self._log_path(path, T, np.stack([c.K for c in wc]), np.array([[c.width, c.height] for c in wc]), depth)
        info = (
            m.info()
            if hasattr(m, "info")
            else {"num_landmarks": len(P), "num_frames": len(T), "extractor": getattr(m, "extractor", "?")}
        )
        rows = [(k, v) for k, v in info.items() if not isinstance(v, (dict, list))]
        rows.append(("landmark colours", color_by.replace("_", " ") + " (viridis, 2nd-98th percentile)"))
        if len(q):
            rows.append(
                (
                    "voxel colours",
                    f"quality = PSNR dB, {np.percentile(q, 2):.1f} (dark) .. {np.percentile(q, 98):.1f} (yellow)",
                )
            )
        doc_path = "map" if path == "world/map" else f"map/{path.split('/')[-1]}"
        self.rec.log(
            doc_path, rr.TextDocument(markdown_table(rows, ("", "")), media_type=rr.MediaType.MARKDOWN), static=True
        )

    def _log_path(
        self, path: str, T: np.ndarray, Ks: np.ndarray, sizes: np.ndarray, depth: float, line: bool = True
    ) -> None:
        """Static camera path: a line through the centres and (at most MAX_FRUSTUMS) wireframe frustums."""
        if line:
            c = geometry.camera_centers(T)
            self.rec.log(
                f"{path}/trajectory", rr.LineStrips3D([c], colors=[GREY], radii=rr.Radius.ui_points(1.0)), static=True
            )
        sel = np.unique(np.linspace(0, len(T) - 1, min(len(T), MAX_FRUSTUMS)).round().astype(int))
        seg = frustum_segments(T[sel], Ks[sel], sizes[sel], depth)
        self.rec.log(
            f"{path}/trajectory/frustums",
            rr.LineStrips3D(seg, colors=[GREY], radii=rr.Radius.ui_points(0.75)),
            static=True,
        )

    # -- generic ------------------------------------------------------------------------------------
    @_guarded
    def log_text(self, path: str, text: str, markdown: bool = True) -> None:
        self._at()
        self.rec.log(
            path,
            rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN if markdown else rr.MediaType.TEXT),
            static=True,
        )

    @_guarded
    def log_points(self, path: str, positions, color=(240, 60, 50), radius: float = 3.0) -> None:
        """Static 3D points, e.g. the landmarks ``prune`` removed."""
        self._at()
        self.rec.log(
            path,
            rr.Points3D(
                np.asarray(positions, np.float64).reshape(-1, 3), colors=[color], radii=rr.Radius.ui_points(radius)
            ),
            static=True,
        )
