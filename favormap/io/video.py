"""Frames of a video, written as images for pose estimation (:mod:`favormap.io.sfm`).

A frame is kept every ``every`` frames, or, by default, when the camera has moved: when the median
displacement of corners tracked (Lucas-Kanade optical flow) from the last kept frame reaches
``motion`` times the frame's width. A still camera then adds no frames, a fast one adds many.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg")
# the keyframe test runs on grey frames of this width
_FLOW_WIDTH = 320
_MIN_CORNERS = 20


def is_video(path) -> bool:
    """Whether ``path`` is a file with a video's suffix."""
    p = Path(path)
    return p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES


@dataclass
class VideoFrames:
    """The frames kept from a video: image names (in ``folder``), their frame numbers, how many were read."""

    folder: Path
    names: list[str]
    frame_numbers: list[int]
    frames_read: int
    rule: str  # "one in 5 frames" or "motion >= 5 % of the width"


def _small_grey(frame: np.ndarray) -> np.ndarray:
    import cv2

    h, w = frame.shape[:2]
    s = _FLOW_WIDTH / w
    small = cv2.resize(frame, (_FLOW_WIDTH, max(1, round(h * s))), interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(small, cv2.COLOR_BGR2GRAY)


def _moved(last: np.ndarray, grey: np.ndarray) -> float:
    """Median displacement of corners of ``last`` tracked into ``grey``, as a share of the width (1: lost)."""
    import cv2

    pts = cv2.goodFeaturesToTrack(last, 200, 0.01, 7)
    if pts is None or len(pts) < _MIN_CORNERS:
        return float(np.mean(np.abs(last.astype(np.float32) - grey)) > 8)  # textureless: keep on a change
    nxt, ok, _ = cv2.calcOpticalFlowPyrLK(last, grey, pts, None)
    ok = ok.ravel() == 1
    if ok.sum() < _MIN_CORNERS:
        return 1.0
    return float(np.median(np.linalg.norm((nxt - pts)[ok].reshape(-1, 2), axis=1)) / last.shape[1])


def extract_frames(
    video,
    folder,
    every: int = 0,
    motion: float = 0.05,
    progress: Callable | None = None,
) -> VideoFrames:
    """Write the kept frames of ``video`` to ``folder`` as ``frame_NNNNNN.jpg`` (N: the frame number).
    ``every`` > 0 keeps frames 0, every, 2 every, ...; 0 keeps them by ``motion`` (module doc).
    ``progress(stage, done, total)`` sees the frames read."""
    import cv2

    if every < 0 or (every == 0 and not 0 < motion < 1):
        raise InputError(f"frames of a video: every N >= 1 frames or a motion in (0, 1), not {every}, {motion}")
    cap = cv2.VideoCapture(str(video))
    if not cap.isOpened():
        raise InputError(f"cannot read the video {video}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    total = max(int(cap.get(cv2.CAP_PROP_FRAME_COUNT)), 0)
    names, numbers, last, i = [], [], None, 0
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            grey = _small_grey(frame) if every == 0 else None
            if every > 0 and i % every == 0 or every == 0 and (last is None or _moved(last, grey) >= motion):
                name = f"frame_{i:06d}.jpg"
                if not cv2.imwrite(str(folder / name), frame, [cv2.IMWRITE_JPEG_QUALITY, 95]):
                    raise InputError(f"cannot write {folder / name}")
                names.append(name)
                numbers.append(i)
                last = grey
            i += 1
            if progress is not None:
                progress("video", i, max(total, i))
    finally:
        cap.release()
    if not names:
        raise InputError(f"no frame could be read from the video {video}")
    rule = f"one in {every} frames" if every else f"motion >= {100 * motion:g} % of the width"
    return VideoFrames(folder, names, numbers, i, rule)
