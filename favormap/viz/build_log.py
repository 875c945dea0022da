"""The build recording: frames, tracks, landmarks and the voxel training, stage by stage
(timeline ``frame`` for mapping frames, ``iteration`` for training)."""

from __future__ import annotations

import numpy as np
import rerun as rr

from .. import geometry
from .base import (
    FRAME_IMAGE_SIDE,
    GREY,
    RecordingBase,
    _guarded,
    _jpeg,
    _pinhole,
    _scaled_K,
    _transform,
    colormap,
    frustum_depth,
    id_colors,
    markdown_table,
    view_coordinates,
)


class BuildLog(RecordingBase):
    """What :func:`favormap.build.build_map` does, through :meth:`build_observer`."""

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
        self.rec.log(
            "world/map/landmarks",
            rr.Points3D(lms.positions, colors=colormap(lengths, lo, hi), radii=rr.Radius.ui_points(2.0)),
            static=True,
        )
        if self._frame_scale is not None and len(lms):
            # now that the scene depth is known, redraw the frustums at 1/5 of the median viewing distance
            centers = geometry.camera_centers(self._frame_T)[lms.tracks.frame_idx]
            dist = np.linalg.norm(lms.positions[lms.tracks.track_of_obs] - centers, axis=1)
            self._depth = frustum_depth(self._frame_T, dist)
            self._log_path(
                "world/map",
                self._frame_T,
                np.stack([c.K for c in self._frame_cams]),
                np.array([[c.width, c.height] for c in self._frame_cams]),
                self._depth,
                line=False,
            )
            for i, (K, w, h) in enumerate(self._frame_pinholes):
                self._at("frame", i)
                self.rec.log("world/camera", _pinhole(K, w, h, self._depth))
            obs_colors = colormap(lengths[lms.tracks.track_of_obs], lo, hi)
            self._per_frame_points(
                "world/camera/image/landmarks", lms.tracks.frame_idx, lms.tracks.xy, obs_colors, 3.5, len(ff.features)
            )

    def _per_frame_points(self, path, frame_idx, xy, colors, radius, n_frames) -> None:
        order = np.argsort(frame_idx, kind="stable")
        bounds = np.searchsorted(np.asarray(frame_idx)[order], np.arange(n_frames + 1))
        for f in range(n_frames):
            sel = order[bounds[f] : bounds[f + 1]]
            self._at("frame", f)
            self.rec.log(
                path,
                rr.Points2D(
                    np.asarray(xy, np.float64)[sel] * self._frame_scale[f],
                    colors=colors[sel],
                    radii=rr.Radius.ui_points(radius),
                ),
            )

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
            self.rec.log(
                "world/map/voxels",
                rr.Boxes3D(centers=P, half_sizes=half, colors=colormap(m.quality), radii=rr.Radius.ui_points(0.5)),
                static=True,
            )
        rows = [(k, f"{v:.3f}") for k, v in timings.items()] + [("**total**", f"**{sum(timings.values()):.3f}**")]
        self.rec.log(
            "build/timings",
            rr.TextDocument(
                "### seconds per stage\n\n" + markdown_table(rows, ("stage", "s")), media_type=rr.MediaType.MARKDOWN
            ),
            static=True,
        )
        st = (getattr(m, "provenance", None) or {}).get("stats", {})
        if st:
            rows = [(k, f"{v:.4g}" if isinstance(v, float) else v) for k, v in st.items()]
            self.rec.log(
                "build/stats",
                rr.TextDocument(
                    "### build statistics\n\n" + markdown_table(rows, ("", "")), media_type=rr.MediaType.MARKDOWN
                ),
                static=True,
            )
