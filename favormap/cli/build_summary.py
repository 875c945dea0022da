"""The summary of favormap build: its figures (JSON) and their lines."""

from __future__ import annotations

from pathlib import Path

from .common import human_size, reproj_error_line, voxel_memory_line


def summary(m, path: Path) -> dict:
    from ..build_config import default_max_epipolar
    from ..mapfile import Map
    from ..mapfile.model import built_for_exact_poses, map_aligns_by_default

    st = m.provenance["stats"]
    with Map.open(path) as written:  # metadata only
        voxel_memory = written.info()["voxel_memory_bytes"]
    return {
        **st,
        "exact_poses": built_for_exact_poses(m.provenance),
        "aligns_by_default": map_aligns_by_default(m.provenance),
        "keypoint_precision_px": default_max_epipolar(m.extractor),
        "file": str(path),
        "file_size": path.stat().st_size,
        "voxel_memory_bytes": voxel_memory,
        "timings": m.provenance["timings"],
        "total_seconds": round(sum(m.provenance["timings"].values()), 2),
        **({"poses": m.provenance["poses"]} if "poses" in m.provenance else {}),
    }


# the build summary suggests a looser --max-epipolar when fewer than this share of the mutual matches within
# 3x the limit lie within it (accurate poses keep ~0.85, poses off by a fraction of a degree ~0.4)
_EPIPOLAR_HINT = 0.6
# ... and suggests --exact-poses when nearly every match within 3x the limit lies within it and the landmarks
# reproject within this many px of their observations, as on synthetic scenes (~0.1 px) and not on real
# captures with SfM poses (0.3-0.45 px)
_EXACT_HINT_SHARE = 0.95
_EXACT_HINT_PX = 0.15


def print_summary(s: dict) -> None:
    from ..pose_refinement import poses_need_refinement

    print(f"frames              {s['frames']}")
    kept, kept3 = s.get("epipolar_kept"), s.get("epipolar_kept_3x")
    line = f"tracks              {s['tracks']}"
    if kept is not None and kept3:
        px = s["max_epipolar_px"]
        line += f"  (mutual matches within {px:g} px of their epipolar line: {100 * kept:.0f} %, "
        line += f"within {3 * px:g} px: {100 * kept3:.0f} %"
        # accurate poses put nearly every right match within the limit; wrong matches spread evenly
        line += (
            "; many beyond: poses less accurate than the limit? leave --max-epipolar out to measure it)"
            if kept < _EPIPOLAR_HINT * kept3 and not s.get("epipolar_measured")
            else ")"
        )
    print(line)
    if s.get("epipolar_measured"):
        line = f"epipolar limit      {s['max_epipolar_px']:.2f} px, measured"
        med = s.get("epipolar_median_px")
        line += f" (right matches' median distance {med:.2f} px)" if med is not None else " (too few matches: floor)"
    print(line)
    line = f"landmarks           {s['landmarks']}  (triangulated {s['triangulated']}"
    if "max_landmarks" in s:  # longest tracks first; two-view tracks fill what the longer ones leave
        line += f"; budget {s['max_landmarks']}"
        if s.get("coverage_landmarks"):
            line += f" + {s['coverage_landmarks']} for frames that saw fewer than {s['min_frame_landmarks']}"
        line += f", {s['two_view_landmarks']} of two views"
    print(line + ")")
    print(f"mean track length   {s['mean_track_length']:.2f}")
    print(reproj_error_line(s["median_reproj_error_px"]))
    if s.get("exact_poses"):
        print("exact poses         tracks aligned through the landmarks' planes; localize aligns by default")
    elif s.get("aligns_by_default"):
        print("keypoint alignment  observations' pixels stored; localize aligns the query keypoints by default")
    elif (
        kept
        and kept3
        and kept >= _EXACT_HINT_SHARE * kept3
        and s["median_reproj_error_px"] <= _EXACT_HINT_PX
        and "poses" not in s
    ):
        print(
            "                    (the tracks fit the poses as exact ones do: if they are, from a simulator or motion "
            "capture, --exact-poses localizes more precisely)"
        )
    if "camera_rotation_deg" in s and s.get("camera_rotation_applied", True):
        rms = s["camera_rotation_rms_px"]
        print(
            f"camera rotation     {s['camera_rotation_deg']:.2f} deg against the given poses (estimated from the "
            f"tracks; their RMS reprojection {rms[0]:.2f} -> {rms[1]:.2f} px): localize takes and reports poses in "
            "their frame"
        )
    elif "camera_rotation_deg" in s:
        print(
            f"camera rotation     none applied: the estimate ({s['camera_rotation_deg']:.2f} deg) is no shared "
            f"calibration, the two halves of the frames give estimates {s['camera_rotation_halves_apart_deg']:.2f} "
            "deg apart"
        )
    if s.get("poses_refined"):
        rms = s["pose_refinement_rms_px"]
        print(
            f"poses refined       cameras moved {s['pose_center_shift_median']:.3g} (median), turned "
            f"{s['pose_rotation_change_median_deg']:.2f} deg; tracks' RMS reprojection {rms[0]:.2f} -> {rms[1]:.2f} px"
        )
    elif poses_need_refinement(s.get("epipolar_median_px", float("nan")), s.get("keypoint_precision_px", 1.0)):
        print(
            "                    (the right matches lie farther from their epipolar lines than the keypoints' "
            "precision: if the poses come from motion capture or a tracker, --refine-poses fits them to the images)"
        )
    print(f"median PSNR         {s['median_psnr']:.2f} dB   (median cosine {s['median_cosine']:.3f})")
    print(f"file                {s['file']}  ({human_size(s['file_size'])})")
    if "voxel_memory_bytes" in s:
        print(voxel_memory_line(s["voxel_memory_bytes"]))
    print(
        "seconds per stage   "
        + ", ".join(f"{k} {v:.1f}" for k, v in s["timings"].items())
        + f"  (total {s['total_seconds']:.1f})"
    )
