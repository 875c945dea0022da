"""The settings of ``extend`` (:class:`ExtendConfig`). No numpy or torch import: the CLI reads its
defaults from here."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class ExtendConfig:
    """Settings of :func:`favormap.ops.extend.extend_map`. The extraction, tracking, triangulation and
    training settings are the map's own (its provenance's build config); these are the extension's."""

    # 4x4 similarity new_to_map (x_map = s R x_new + t) moving the new sequence's poses into the map's frame
    # (None: they are in it already)
    transform: list | None = None
    # estimate that similarity first: a quick map of the new sequence aligned to the map (favormap.ops.align)
    align: bool = False
    # a new observation is attached to a landmark only within this many degrees beyond the landmark's existing
    # viewing cone (its view_angle around view_dir), and only within its trained distance range
    view_cone_deg: float = 15.0
    # a landmark projected into a new frame takes the most similar keypoint within this many pixels (None: the
    # epipolar limit the map's tracking held its matches to, given or measured by its build: a projection is
    # trusted as far as the poses were)
    match_radius_px: float | None = None
    # least cosine similarity of that keypoint's descriptor with the landmark's mean descriptor
    # (None: the map's tracking threshold, BuildConfig.min_similarity)
    min_similarity: float | None = None
    # the extended map's landmark budget, chosen as a build chooses them (the longest tracks first, then the
    # best remaining tracks of frames that see fewer than the build's min_frame_landmarks) among the map's
    # landmarks, grown by the new frames, and the new frames' own tracks. None: the map's build budget
    max_landmarks: int | None = None
    format: str | None = None  # the new sequence's format (None: detected)
    device: str = "cpu"  # torch device of the voxel training
