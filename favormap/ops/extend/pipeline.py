"""The stages of the extension, in order: the new frames' features and tracks, their matches to the map's
landmarks, the triangulation within the landmark budget, the training, the extended map written."""

from __future__ import annotations

import time
from contextlib import contextmanager
from pathlib import Path

from ...errors import InputError
from ..extend_config import ExtendConfig
from .api import ExtendSummary
from .assemble import assemble_map
from .frames import frames_in_map, output_frames
from .matching import NewFrames, attach
from .training import train_landmarks
from .triangulate import triangulate_landmarks


class _Stages:
    """``with stages(name):`` times a stage into ``timings`` (s) and reports its end to ``progress``."""

    def __init__(self, timings: dict, progress):
        self.timings, self.progress = timings, progress or (lambda *a: None)

    @contextmanager
    def __call__(self, name: str):
        t = time.perf_counter()
        try:
            yield
        finally:
            self.timings[name] = round(time.perf_counter() - t, 3)
            self.progress(name, 1, 1)


def run_extension(m, seq, output: Path, cfg, config: ExtendConfig, progress, timings: dict) -> ExtendSummary:
    """The extension of the map ``m`` (MapData, built with ``cfg``) by the frames of ``seq``, written to ``output``."""
    from ...mapfile import write_map

    warnings = _check_input(m, seq, cfg)
    stage = _Stages(timings, progress)
    new = _new_frames(seq, cfg, progress, stage)
    with stage("match"):
        att = attach(m, new, cfg, config)
    frames = output_frames(m, seq, new.ff)
    with stage("triangulate"):
        lms = triangulate_landmarks(m, new, att, frames, cfg, config)
    with stage("train"):
        trained = train_landmarks(m, lms, new, frames, cfg)
    L0, removed = m.num_landmarks, len(lms.dropped)
    summary = ExtendSummary(
        output=output,
        frames_before=m.num_frames,
        frames_added=len(seq.frames),
        landmarks_before=L0,
        landmarks_grown=lms.n_grown,
        landmarks_retrained=int(trained.retrain.sum()),
        observations_added=lms.observations_added,
        landmarks_added=lms.n_new,
        landmarks_removed=removed,
        landmarks_after=L0 + lms.n_new - removed,
        timings=timings,
        warnings=warnings,
    )
    with stage("write"):
        record = _record(m, seq, summary, att.radius_px, att.min_similarity, config)
        write_map(assemble_map(m, seq, new, frames, lms, trained, cfg, record), output)
    return summary


def _check_input(m, seq, cfg) -> list[str]:
    """InputError where the map cannot take ``seq`` (the checks of a build, then the build config against
    the map); else the warnings about the extension."""
    from ...build import check_build_input

    check_build_input(seq, cfg)
    if cfg.max_side != m.max_side or cfg.extractor != m.extractor:
        raise InputError("the map's build configuration does not match the map (max_side, extractor)")
    warnings: list[str] = []
    again = frames_in_map(m, seq)
    if again:
        warnings.append(
            f"{len(again)} of the {len(seq.frames)} new frames are in the map already (the same name and pose, "
            f"e.g. {again[0]}): they are added again and their observations count twice"
        )
    if cfg.refine_poses:
        warnings.append(
            "the map's poses were refined by bundle adjustment (build --refine-poses) and the new frames' are "
            "used as given: landmarks seen from both agree only as well as the given poses do"
        )
    return warnings


def _new_frames(seq, cfg, progress, stage: _Stages) -> NewFrames:
    """The extraction and tracking stages: the new frames' features with the map's extractor settings,
    tracked among themselves as a build tracks them."""
    from ...build import ExtractorSpec, extract_sequence, track_frames

    extractor = ExtractorSpec(cfg.extractor, cfg.max_keypoints)
    with stage("extract"):
        ff = extract_sequence(seq, extractor, cfg.max_side, progress)
    with stage("track"):
        tracks = track_frames(ff, cfg)
    return NewFrames(ff, tracks, extractor)


_COUNTS = (
    "frames_before",
    "frames_added",
    "landmarks_before",
    "landmarks_grown",
    "landmarks_retrained",
    "observations_added",
    "landmarks_added",
    "landmarks_removed",
)


def _record(m, seq, summary: ExtendSummary, radius_px: float, min_similarity: float, config: ExtendConfig) -> dict:
    """The extension as the provenance's ``extensions`` records it."""
    return {
        "source_map": str(m.provenance.get("source_map_path", "")) or None,
        "sequence": str(seq.root),
        "sequence_format": seq.format,
        **{k: getattr(summary, k) for k in _COUNTS},
        "view_cone_deg": config.view_cone_deg,
        "match_radius_px": radius_px,
        "min_similarity": float(min_similarity),
        "timings": summary.timings,
    }
