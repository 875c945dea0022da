"""The rerun recorder: one dedicated ``rr.RecordingStream`` per command (never the global one, so
favormap is safe to embed in programs that use rerun themselves).

Timelines: ``frame`` (build: one step per mapping frame), ``iteration`` (build: voxel training),
``query`` (localize/eval: one step per query). Everything that does not change over time (map
landmarks, voxels, camera path, timings) is logged static. The entity paths are listed in
``docs/rerun.md``; keep the two in sync.

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
from ..errors import InputError
from . import DEFAULT_PORT
from .blueprint import blueprint_for

# preview sizes (longest side, px) and JPEG quality of the logged images
FRAME_IMAGE_SIDE = 320
QUERY_IMAGE_SIDE = 640
JPEG_QUALITY = 80
MAX_FRUSTUMS = 300  # static camera-path frustums drawn at most (evenly subsampled)

GREY = (150, 150, 150)
INLIER = (40, 220, 80)
OUTLIER = (240, 60, 50)
PRIOR = (255, 160, 0)
GT = (60, 200, 255)
SERIES = {"rendered": (70, 130, 255), "mean": (255, 140, 0), "prior": (150, 150, 150)}

# viridis, 9 samples (0, 1/8, ..., 1)
_VIRIDIS = np.array([[68, 1, 84], [71, 44, 122], [59, 81, 139], [44, 113, 142], [33, 144, 141],
                     [39, 173, 129], [92, 200, 99], [170, 220, 50], [253, 231, 37]], np.float64)


# ---------------------------------------------------------------------------------------------
# small helpers
# ---------------------------------------------------------------------------------------------
def colormap(values, lo: float | None = None, hi: float | None = None) -> np.ndarray:
    """Values -> viridis RGB uint8 (N, 3); ``lo``/``hi`` default to the 2nd/98th percentiles."""
    v = np.asarray(values, np.float64).ravel()
    if len(v) == 0:
        return np.zeros((0, 3), np.uint8)
    finite = v[np.isfinite(v)]
    if lo is None:
        lo = float(np.percentile(finite, 2)) if len(finite) else 0.0
    if hi is None:
        hi = float(np.percentile(finite, 98)) if len(finite) else 1.0
    t = np.clip((np.nan_to_num(v, nan=lo) - lo) / max(hi - lo, 1e-12), 0.0, 1.0) * (len(_VIRIDIS) - 1)
    i = np.minimum(t.astype(np.int64), len(_VIRIDIS) - 2)
    f = (t - i)[:, None]
    return np.round(_VIRIDIS[i] * (1 - f) + _VIRIDIS[i + 1] * f).astype(np.uint8)


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


def _project(K: np.ndarray, cam_from_world: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of world points and a mask of those in front of the camera."""
    Xc = geometry.transform_points(cam_from_world, np.asarray(X, np.float64).reshape(-1, 3))
    z = Xc[:, 2]
    front = z > 1e-9
    uv = (Xc @ K.T)[:, :2] / np.where(front, z, 1.0)[:, None]
    return uv, front


def frustum_segments(cam_from_world: np.ndarray, Ks: np.ndarray, sizes: np.ndarray, depth: float) -> np.ndarray:
    """Wireframe frustums as line segments (N*8, 2, 3): 4 rays from the centre + the image rectangle
    at ``depth`` in front of each camera."""
    T = np.asarray(cam_from_world, np.float64).reshape(-1, 4, 4)
    n = len(T)
    if n == 0:
        return np.zeros((0, 2, 3))
    w, h = sizes[:, 0].astype(np.float64), sizes[:, 1].astype(np.float64)
    px = np.stack([np.stack([np.zeros(n), np.zeros(n)], 1), np.stack([w, np.zeros(n)], 1),
                   np.stack([w, h], 1), np.stack([np.zeros(n), h], 1)], 1)  # (n, 4, 2)
    hom = np.concatenate([px, np.ones((n, 4, 1))], -1)
    rays = np.einsum("nij,nkj->nki", np.linalg.inv(Ks), hom)
    rays = rays / rays[..., 2:3] * depth
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


def rerun_executable() -> str | None:
    """The ``rerun`` CLI shipped with rerun-sdk (also reachable as ``python -m rerun``)."""
    import shutil

    try:
        import rerun_cli

        exe = Path(rerun_cli.__file__).parent / "rerun"
        if exe.is_file() and os.access(exe, os.X_OK):
            return str(exe)
    except ImportError:
        pass
    return shutil.which("rerun")


def analytics_opt_in() -> bool:
    """True when the user explicitly allowed the viewer's anonymous usage analytics."""
    return os.environ.get("RERUN_ANALYTICS", "").strip().lower() in ("1", "true", "yes", "on")


def viewer_environment() -> dict:
    """Environment of a spawned viewer. rerun 0.41 ignores ``RERUN_ANALYTICS``: its viewer turns
    analytics off when ``CI`` is set (or after ``rerun analytics disable``), so the child gets
    ``CI=1`` unless the user opted in with ``RERUN_ANALYTICS=true``. Only the child's environment
    changes, never ours."""
    env = dict(os.environ)
    env["RERUN_APP_ONLY"] = "true"  # what rr.spawn sets too: a viewer app, no first-run prompts
    if not analytics_opt_in():
        env.setdefault("CI", "1")
    return env


def _port_open(port: int, host: str = "127.0.0.1", timeout: float = 0.2) -> bool:
    import socket

    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except OSError:
        return False


def _check_url(url: str) -> None:
    """Reject malformed --rerun-connect URLs; warn (once, early) when nothing listens there yet."""
    from urllib.parse import urlsplit

    u = urlsplit(url)
    if not u.scheme.startswith("rerun") or not u.hostname:
        raise InputError(f"--rerun-connect expects a URL like rerun+http://127.0.0.1:{DEFAULT_PORT}/proxy, got {url!r}")
    try:
        port = u.port or (443 if u.scheme.endswith("https") else DEFAULT_PORT)
    except ValueError:
        raise InputError(f"--rerun-connect: bad port in {url!r}") from None
    if not _port_open(port, u.hostname, timeout=1.0):
        print(f"favormap: warning: no rerun viewer listens at {url} yet (start one with `rerun`); "
              "data logged before it starts may be lost", file=sys.stderr)


def spawn_viewer(port: int = DEFAULT_PORT, memory_limit: str = "75%", wait_s: float = 30.0) -> None:
    """Start a detached local rerun viewer listening on ``port`` (unless one already listens there)
    and wait until it accepts connections. Raises :class:`InputError` when it cannot start (no
    display, no executable)."""
    import subprocess
    import tempfile
    import time

    if _port_open(port):
        return  # a viewer (or another rerun server) is already listening: reuse it
    exe = rerun_executable()
    if exe is None:
        raise InputError("the rerun viewer executable was not found (it ships with rerun-sdk); "
                         "use --rerun-save FILE.rrd and open the file with `rerun FILE.rrd`")
    err = tempfile.TemporaryFile()
    try:
        proc = subprocess.Popen([exe, "--port", str(port), "--memory-limit", memory_limit, "--expect-data-soon",
                                 "--hide-welcome-screen"], env=viewer_environment(), stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=err, start_new_session=True)
        t_end = time.monotonic() + wait_s
        while time.monotonic() < t_end:
            if proc.poll() is not None:
                err.seek(0)
                lines = [ln for ln in err.read().decode(errors="replace").splitlines() if "rror" in ln]
                why = lines[-1].strip()[:300] if lines else f"exit code {proc.returncode}"
                raise InputError(f"the rerun viewer could not start ({why}); use --rerun-save FILE.rrd "
                                 "(or --rerun-connect URL of a viewer running elsewhere)")
            if _port_open(port):
                return
            time.sleep(0.1)
        # neither listening nor exited (e.g. a loaded machine without a display): do not stream into nothing
        proc.kill()
        raise InputError(f"the rerun viewer could not start (no connection on port {port} within {wait_s:.0f} s); "
                         "use --rerun-save FILE.rrd (or --rerun-connect URL of a viewer running elsewhere)")
    finally:
        err.close()


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
            print(f"favormap: rerun logging failed ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}); "
                  "continuing without it", file=sys.stderr)
            return None

    return wrapper


# ---------------------------------------------------------------------------------------------
# the recorder
# ---------------------------------------------------------------------------------------------
class Recording:
    """Logs what a favormap command does into one rerun recording.

    ``kind`` picks the default layout (build, localize, eval, view, merge, prune). Sinks: ``save``
    (an .rrd file), ``connect`` (a gRPC URL), ``spawn`` (start a local viewer); any combination."""

    def __init__(self, app_id: str, kind: str = "view", *, spawn: bool = False, save=None, connect: str | None = None,
                 map_=None, methods: list[str] | None = None, port: int = DEFAULT_PORT, strict: bool | None = None):
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
        if spawn:
            spawn_viewer(port)
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
        try:
            self.rec.flush(timeout_sec=10.0)
        except Exception as e:  # noqa: BLE001 - the command itself succeeded
            if self.strict:
                raise
            ok = False
            print(f"favormap: warning: the rerun recording was not fully delivered "
                  f"({str(e).splitlines()[0] if str(e) else type(e).__name__})", file=sys.stderr)
        finally:
            self.rec.disconnect()
        return ok

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
        depth = frustum_depth(T, None if depth_range is None or len(depth_range) == 0 else np.asarray(depth_range)[:, 0])
        if path == "world/map":
            self._map_positions = P
            self._map_max_side = int(getattr(m, "max_side", 640) or 0)
            self._depth = depth
            ids = np.asarray(getattr(m, "frame_camera_ids", []))
            cams = getattr(m, "cameras", {}) or {}
            self._map_camera = cams.get(int(ids[0])) if len(ids) and int(ids[0]) in cams else next(iter(cams.values()), None)
        vals = q if color_by == "quality" else np.asarray(m.track_length, np.float64)
        self.rec.log(f"{path}/landmarks", rr.Points3D(P, colors=colormap(vals), radii=rr.Radius.ui_points(2.0)), static=True)
        if voxels and len(P):
            half = np.repeat(np.asarray(m.voxel_size, np.float64)[:, None] / 2, 3, axis=1)
            self.rec.log(f"{path}/voxels", rr.Boxes3D(centers=P, half_sizes=half, colors=colormap(q),
                                                      radii=rr.Radius.ui_points(0.5)), static=True)
        if len(T):
            cams = getattr(m, "cameras", {}) or {}
            ids = np.asarray(getattr(m, "frame_camera_ids", np.zeros(len(T), int)))
            wcams = {cid: working_camera(c, self._map_max_side or None) for cid, c in cams.items()}
            if wcams:
                fallback = next(iter(wcams.values()))
                wc = [wcams.get(int(i), fallback) for i in ids]
                self._log_path(path, T, np.stack([c.K for c in wc]), np.array([[c.width, c.height] for c in wc]), depth)
        info = m.info() if hasattr(m, "info") else {"num_landmarks": len(P), "num_frames": len(T), "extractor": getattr(m, "extractor", "?")}
        rows = [(k, v) for k, v in info.items() if not isinstance(v, (dict, list))]
        rows.append(("landmark colours", color_by.replace("_", " ") + " (viridis, 2nd-98th percentile)"))
        if len(q):
            rows.append(("voxel colours", f"quality = PSNR dB, {np.percentile(q, 2):.1f} (dark) .. {np.percentile(q, 98):.1f} (yellow)"))
        doc_path = "map" if path == "world/map" else f"map/{path.split('/')[-1]}"
        self.rec.log(doc_path, rr.TextDocument(markdown_table(rows, ("", "")), media_type=rr.MediaType.MARKDOWN), static=True)

    def _log_path(self, path: str, T: np.ndarray, Ks: np.ndarray, sizes: np.ndarray, depth: float, line: bool = True) -> None:
        """Static camera path: a line through the centres and (at most MAX_FRUSTUMS) wireframe frustums."""
        if line:
            c = geometry.camera_centers(T)
            self.rec.log(f"{path}/trajectory", rr.LineStrips3D([c], colors=[GREY], radii=rr.Radius.ui_points(1.0)), static=True)
        sel = np.unique(np.linspace(0, len(T) - 1, min(len(T), MAX_FRUSTUMS)).round().astype(int))
        seg = frustum_segments(T[sel], Ks[sel], sizes[sel], depth)
        self.rec.log(f"{path}/trajectory/frustums", rr.LineStrips3D(seg, colors=[GREY], radii=rr.Radius.ui_points(0.75)), static=True)

    # -- build --------------------------------------------------------------------------------------
    def build_observer(self):
        """A :class:`favormap.build.BuildObserver` that logs every stage into this recording."""
        from ..build import BuildObserver

        rec = self

        class _BuildRecorder(BuildObserver):
            wants_images = True

            def on_frames(self, seq, ff, images):
                rec.log_frames(ff, images)
                if images is not None:
                    images.clear()  # logged: free the working images for the rest of the build

            def on_tracks(self, tracks, ff):
                rec.log_tracks(tracks, ff)

            def on_landmarks(self, lms, ff):
                rec.log_landmarks(lms, ff)

            def on_train_step(self, iteration, loss, psnr):
                rec.log_train_step(iteration, loss, psnr)

            def on_map(self, m, timings):
                rec.log_build_result(m, timings)

        return _BuildRecorder()

    @_guarded
    def log_frames(self, ff, images: list | None) -> None:
        """Per frame (timeline ``frame``): camera pose + pinhole, downscaled image, keypoints; static:
        the camera path with frustums."""
        T = np.asarray(ff.cam_from_world, np.float64)
        cams = ff.cameras
        Ks = np.stack([c.K for c in cams])
        sizes = np.array([[c.width, c.height] for c in cams])
        self._depth = frustum_depth(T)
        self._frame_cams = cams
        self._frame_scale = np.array([min(1.0, FRAME_IMAGE_SIDE / max(c.width, c.height)) for c in cams])
        self._at()
        vc = view_coordinates(T)
        if vc is not None:
            self.rec.log("world", vc, static=True)
        self._log_path("world/map", T, Ks, sizes, self._depth)
        self._frame_T = T
        self._frame_pinholes = []
        for i, cam in enumerate(cams):
            self._at("frame", i)
            s = self._frame_scale[i]
            if images is not None and i < len(images):
                enc, s, w, h = _jpeg(images[i], FRAME_IMAGE_SIDE)
                self._frame_scale[i] = s
            else:
                enc, w, h = None, max(1, round(cam.width * s)), max(1, round(cam.height * s))
            self._frame_pinholes.append((_scaled_K(cam.K, s), w, h))
            self.rec.log("world/camera", _transform(T[i]), _pinhole(_scaled_K(cam.K, s), w, h, self._depth))
            if enc is not None:
                self.rec.log("world/camera/image", enc)
            kp = np.asarray(ff.features[i].keypoints, np.float64) * s
            self.rec.log("world/camera/image/keypoints", rr.Points2D(kp, colors=[GREY], radii=rr.Radius.ui_points(1.5)))

    @_guarded
    def log_tracks(self, tracks, ff) -> None:
        """Per frame: the tracked keypoints, one colour per track."""
        if self._frame_scale is None:
            return
        tid = tracks.track_of_obs
        colors = id_colors(tid)
        self._per_frame_points("world/camera/image/tracks", tracks.frame_idx, tracks.xy, colors, 2.5, len(ff.features))

    @_guarded
    def log_landmarks(self, lms, ff) -> None:
        """Static: triangulated (selected) landmarks coloured by track length; per frame: their
        observations, same colours."""
        lengths = lms.tracks.lengths.astype(np.float64)
        lo, hi = (float(lengths.min()), float(np.percentile(lengths, 98))) if len(lengths) else (0.0, 1.0)
        self._at()
        self.rec.log("world/map/landmarks", rr.Points3D(lms.positions, colors=colormap(lengths, lo, hi),
                                                        radii=rr.Radius.ui_points(2.0)), static=True)
        if self._frame_scale is not None and len(lms):
            # now that the scene depth is known, redraw the frustums at 1/5 of the median viewing distance
            centers = geometry.camera_centers(self._frame_T)[lms.tracks.frame_idx]
            dist = np.linalg.norm(lms.positions[lms.tracks.track_of_obs] - centers, axis=1)
            self._depth = frustum_depth(self._frame_T, dist)
            self._log_path("world/map", self._frame_T, np.stack([c.K for c in self._frame_cams]),
                           np.array([[c.width, c.height] for c in self._frame_cams]), self._depth, line=False)
            for i, (K, w, h) in enumerate(self._frame_pinholes):
                self._at("frame", i)
                self.rec.log("world/camera", _pinhole(K, w, h, self._depth))
            obs_colors = colormap(lengths[lms.tracks.track_of_obs], lo, hi)
            self._per_frame_points("world/camera/image/landmarks", lms.tracks.frame_idx, lms.tracks.xy, obs_colors, 3.5,
                                   len(ff.features))

    def _per_frame_points(self, path, frame_idx, xy, colors, radius, n_frames) -> None:
        order = np.argsort(frame_idx, kind="stable")
        bounds = np.searchsorted(np.asarray(frame_idx)[order], np.arange(n_frames + 1))
        for f in range(n_frames):
            sel = order[bounds[f]:bounds[f + 1]]
            self._at("frame", f)
            self.rec.log(path, rr.Points2D(np.asarray(xy, np.float64)[sel] * self._frame_scale[f], colors=colors[sel],
                                           radii=rr.Radius.ui_points(radius)))

    @_guarded
    def log_train_step(self, iteration: int, loss: float, psnr: float) -> None:
        """Training curves on the ``iteration`` timeline."""
        if "train/loss" not in self._styled:
            self._at()
            self._series("train/loss", "loss", (230, 90, 60))
            self._series("train/psnr", "PSNR (dB)", (70, 130, 255))
        self._at("iteration", iteration)
        self.rec.log("train/loss", rr.Scalars(float(loss)))
        self.rec.log("train/psnr", rr.Scalars(float(psnr)))

    @_guarded
    def log_build_result(self, m, timings: dict) -> None:
        """Static: voxel boxes coloured by quality, the stage timings and build statistics."""
        self._at()
        P = np.asarray(m.positions, np.float64)
        if len(P):
            half = np.repeat(np.asarray(m.voxel_size, np.float64)[:, None] / 2, 3, axis=1)
            self.rec.log("world/map/voxels", rr.Boxes3D(centers=P, half_sizes=half, colors=colormap(m.quality),
                                                        radii=rr.Radius.ui_points(0.5)), static=True)
        rows = [(k, f"{v:.3f}") for k, v in timings.items()] + [("**total**", f"**{sum(timings.values()):.3f}**")]
        self.rec.log("build/timings", rr.TextDocument("### seconds per stage\n\n" + markdown_table(rows, ("stage", "s")),
                                                      media_type=rr.MediaType.MARKDOWN), static=True)
        st = (getattr(m, "provenance", None) or {}).get("stats", {})
        if st:
            rows = [(k, f"{v:.4g}" if isinstance(v, float) else v) for k, v in st.items()]
            self.rec.log("build/stats", rr.TextDocument("### build statistics\n\n" + markdown_table(rows, ("", "")),
                                                        media_type=rr.MediaType.MARKDOWN), static=True)

    # -- localize / eval ----------------------------------------------------------------------------
    def _working_query(self, image, camera):
        """(working RGB image, working pinhole camera) exactly as the localizer prepares it."""
        from ..io import Camera, prepare_image, read_rgb

        img = image if isinstance(image, np.ndarray) else read_rgb(Path(image))
        h, w = img.shape[:2]
        cam = camera or self._map_camera
        if cam is None or ((w, h) != (cam.width, cam.height) and abs(w / h - cam.width / cam.height) > 0.01):
            f = float(max(w, h))
            cam = Camera("PINHOLE", w, h, [f, f, w / 2, h / 2])  # unknown camera: a plausible guess for display
        elif (w, h) != (cam.width, cam.height):
            cam = cam.scaled(w, h)
        return prepare_image(img, cam, self._map_max_side or None)

    @_guarded
    def log_localization(self, index: int, image, result, prior: np.ndarray, camera=None, gt: np.ndarray | None = None,
                         method: str | None = None) -> None:
        """One query (timeline ``query``): prior, the pose after each iteration, the final pose with the
        query image, its keypoints and the matches (inliers green, outliers red), the inlier
        landmarks in 3D, per-match similarity when the result carries it, and per-query metrics."""
        method = method or self.methods[0]
        base = f"world/query/{method}"
        depth = self._depth or 0.1
        self._at("query", index)
        img, cam = self._working_query(image, camera)
        enc, s, w, h = _jpeg(img, QUERY_IMAGE_SIDE)
        K = _scaled_K(cam.K, s)
        if prior is not None:  # localization without a prior starts from a global coarse pose
            prior = np.asarray(prior, np.float64)
            self.rec.log("world/query/prior", _transform(prior), _pinhole(K, w, h, depth, PRIOR))
        if gt is not None:
            self.rec.log("world/query/gt", _transform(np.asarray(gt, np.float64)), _pinhole(K, w, h, depth, GT))
        # iterations: clear the previous query's, then the path prior -> it1 -> it2 ... and a frustum each
        self.rec.log(f"{base}/iterations", rr.Clear(recursive=True))
        its = list(result.iterations)
        path = ([prior] if prior is not None else []) + [np.asarray(it.cam_from_world) for it in its]
        centers = geometry.camera_centers(np.stack(path)) if path else np.zeros((0, 3))
        self.rec.log(f"{base}/iterations", rr.LineStrips3D([centers], colors=[SERIES.get(method, (70, 130, 255))],
                                                           radii=rr.Radius.ui_points(1.5)))
        for k, it in enumerate(its, 1):
            shade = int(80 + 150 * k / max(len(its), 1))
            self.rec.log(f"{base}/iterations/{k}", _transform(np.asarray(it.cam_from_world)),
                         _pinhole(K, w, h, depth * 0.8, (60, 90, shade)))
        # final estimate with the query image and the 2D matches
        final = np.asarray(result.cam_from_world, np.float64)
        self.rec.log(f"{base}/estimate", _transform(final), _pinhole(K, w, h, depth, INLIER if result.success else OUTLIER))
        self.rec.log(f"{base}/estimate/image", enc)
        kp = np.zeros((0, 2)) if result.keypoints is None else np.asarray(result.keypoints, np.float64) * s
        self.rec.log(f"{base}/estimate/image/keypoints", rr.Points2D(kp, colors=[GREY], radii=rr.Radius.ui_points(1.5)))
        matches = np.zeros((0, 2), np.int64) if result.matches is None else np.asarray(result.matches, np.int64).reshape(-1, 2)
        inl = np.zeros(len(matches), bool)
        if result.inlier_mask is not None and len(result.inlier_mask) == len(matches):
            inl = np.asarray(result.inlier_mask, bool)
        sim = getattr(result, "match_similarity", None)
        sim = None if sim is None or len(sim) != len(matches) else np.asarray(sim, np.float64)
        strips = {True: np.zeros((0, 2, 2)), False: np.zeros((0, 2, 2))}
        if len(matches) and self._map_positions is not None:
            uv, front = _project(K, final, self._map_positions[matches[:, 0]])
            q = kp[matches[:, 1]]
            for flag in (True, False):
                sel = (inl == flag) & front
                strips[flag] = np.stack([q[sel], uv[sel]], 1)
            self.rec.log(f"{base}/inliers", rr.Points3D(self._map_positions[matches[inl, 0]], colors=[INLIER],
                                                        radii=rr.Radius.ui_points(4.0)))
        else:
            self.rec.log(f"{base}/inliers", rr.Points3D(np.zeros((0, 3))))
        self.rec.log(f"{base}/estimate/image/inliers", rr.LineStrips2D(strips[True], colors=[INLIER], radii=rr.Radius.ui_points(1.0)))
        self.rec.log(f"{base}/estimate/image/outliers", rr.LineStrips2D(strips[False], colors=[OUTLIER], radii=rr.Radius.ui_points(1.0)))
        if sim is not None:
            self.rec.log(f"{base}/estimate/image/similarity",
                         rr.Points2D(kp[matches[:, 1]], colors=colormap(sim, 0.5, 1.0), radii=rr.Radius.ui_points(3.0),
                                     labels=[f"{v:.2f}" for v in sim], show_labels=False))
        # per-query metrics
        color = SERIES.get(method, (70, 130, 255))
        last = its[-1] if its else None
        for name, val in (("inliers", result.num_inliers), ("matches", result.num_matches),
                          ("visible", last.num_visible if last else 0),
                          ("time_ms", 1000 * sum(result.timings.values()))):
            self._series(f"metrics/{name}/{method}", method, color)
            self.rec.log(f"metrics/{name}/{method}", rr.Scalars(float(val)))
        if sim is not None and len(sim):
            self._series(f"metrics/similarity/{method}", method, color)
            self.rec.log(f"metrics/similarity/{method}", rr.Scalars(float(np.median(sim))))
        name = Path(str(image)).name if not isinstance(image, np.ndarray) else f"query {index}"
        status = f"localized, {result.num_inliers} inliers / {result.num_matches} matches" if result.success else \
            f"NOT localized: {result.message}"
        if gt is not None:
            dt, dr = geometry.pose_error(final, np.asarray(gt, np.float64))
            pt, pr = geometry.pose_error(prior, np.asarray(gt, np.float64)) if prior is not None else (None, None)
            for metric, val, prior_val in (("translation_error", dt, pt), ("rotation_error_deg", dr, pr)):
                self._series(f"metrics/{metric}/{method}", method, color)
                self.rec.log(f"metrics/{metric}/{method}", rr.Scalars(val))
                if prior_val is not None:
                    self._series(f"metrics/{metric}/prior", "prior", SERIES["prior"])
                    self.rec.log(f"metrics/{metric}/prior", rr.Scalars(prior_val))
            status += f"; error {dt:.4f} / {dr:.2f} deg" + (f" (prior {pt:.4f} / {pr:.2f} deg)" if pt is not None else " (no prior)")
        self.rec.log(f"log/{method}", rr.TextLog(f"{name}: {status}", level="INFO" if result.success else "WARN"))

    def log_eval_query(self, method: str, index: int, outcome, frame=None, camera=None) -> None:
        """One evaluated query (a ``QueryOutcome``): as :meth:`log_localization`, with the ground
        truth and the pose errors (final and prior) on the ``query`` timeline."""
        image = frame.image_path if frame is not None else outcome.name
        self.log_localization(index, image, outcome.result, outcome.prior, camera=camera, gt=outcome.gt, method=method)

    # -- merge / prune -------------------------------------------------------------------------------
    @_guarded
    def log_merge(self, input_paths: list, output_path) -> None:
        """The merged map (as :meth:`log_map`) plus ``world/map/sources``: its landmarks coloured by
        the input map they come from (matched by landmark id; grey: regenerated ids)."""
        from ..mapfile import Map

        with Map.open(output_path) as out:
            self.log_map(out)
            src = np.full(len(out), -1)
            rows = []
            for k, p in enumerate(input_paths):
                with Map.open(p) as mi:
                    hit = np.isin(out.ids, mi.ids) & (src < 0)
                    src[hit] = k
                    rows.append((Path(str(p)).name, len(mi), int(hit.sum())))
            colors = np.where((src >= 0)[:, None], id_colors(np.maximum(src, 0) + 1), np.array(GREY, np.uint8))
            self._at()
            self.rec.log("world/map/sources", rr.Points3D(np.asarray(out.positions, np.float64), colors=colors.astype(np.uint8),
                                                          radii=rr.Radius.ui_points(2.5)), static=True)
            rows.append(("regenerated ids", "", int((src < 0).sum())))
            self.rec.log("map/sources", rr.TextDocument("### merged from\n\n" + markdown_table(rows, ("map", "landmarks", "in output")),
                                                        media_type=rr.MediaType.MARKDOWN), static=True)

    @_guarded
    def log_prune(self, input_path, output_path) -> None:
        """The pruned map (as :meth:`log_map`) plus ``world/removed``: the landmarks pruning dropped."""
        from ..mapfile import Map

        with Map.open(output_path) as out, Map.open(input_path) as src:
            self.log_map(out)
            gone = ~np.isin(src.ids, out.ids)
            self.log_points("world/removed", np.asarray(src.positions)[gone], OUTLIER, 2.0)
            self.log_text("map/removed", f"### pruned\n\nkept {len(out)} of {len(src)} landmarks, removed {int(gone.sum())} "
                                         "(red points in the 3D view: `world/removed`)")

    # -- generic ------------------------------------------------------------------------------------
    @_guarded
    def log_text(self, path: str, text: str, markdown: bool = True) -> None:
        self._at()
        self.rec.log(path, rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN if markdown else rr.MediaType.TEXT), static=True)

    @_guarded
    def log_points(self, path: str, positions, color=(240, 60, 50), radius: float = 3.0) -> None:
        """Static 3D points, e.g. the landmarks ``prune`` removed."""
        self._at()
        self.rec.log(path, rr.Points3D(np.asarray(positions, np.float64).reshape(-1, 3), colors=[color],
                                       radii=rr.Radius.ui_points(radius)), static=True)
