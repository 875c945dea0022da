"""The entry point of the extension: its inputs checked, the map read, the new sequence moved into the
map's frame (given or estimated similarity), then the stages (:mod:`.pipeline`)."""

from __future__ import annotations

import dataclasses
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...errors import InputError
from ..extend_config import ExtendConfig


@dataclass
class ExtendSummary:
    """What :func:`extend_map` did."""

    output: Path
    frames_before: int
    frames_added: int
    landmarks_before: int
    landmarks_grown: int  # existing landmarks that gained observations
    landmarks_retrained: int  # grown landmarks whose grids were trained again (the others render what they see)
    observations_added: int  # new observations of existing landmarks
    landmarks_added: int  # new landmarks from the new frames' own tracks
    landmarks_removed: int  # the map's landmarks left out of the landmark budget (ExtendConfig.max_landmarks)
    landmarks_after: int
    transform: list | None = None  # the new_to_map similarity applied (None: none)
    alignment: dict | None = None  # the estimated alignment (ExtendConfig.align)
    timings: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["output"] = str(self.output)
        return d


def map_build_config(provenance: dict):
    """The :class:`~favormap.build.BuildConfig` a map was built with (its provenance's ``config``)."""
    from ...build_config import BuildConfig
    from ...voxels.config import VoxelConfig

    cfg = dict((provenance or {}).get("config") or {})
    if not cfg or "extractor" not in cfg:
        raise InputError(
            "the map records no build configuration in its provenance (a merged map?): it cannot be extended"
        )
    names = {f.name for f in dataclasses.fields(BuildConfig)}
    vox_names = {f.name for f in dataclasses.fields(VoxelConfig)}
    vox = VoxelConfig(**{k: v for k, v in (cfg.pop("voxel", None) or {}).items() if k in vox_names})
    return BuildConfig(**{k: v for k, v in cfg.items() if k in names}, voxel=vox)


def _check_config(config: ExtendConfig) -> None:
    if not (config.view_cone_deg >= 0 and np.isfinite(config.view_cone_deg)):
        raise InputError(f"view cone must be a finite number of degrees >= 0, not {config.view_cone_deg}")
    if config.match_radius_px is not None and not (config.match_radius_px > 0 and np.isfinite(config.match_radius_px)):
        raise InputError(f"match radius must be > 0 px, not {config.match_radius_px}")
    if config.min_similarity is not None and not -1 <= config.min_similarity <= 1:
        raise InputError(f"min similarity must be in [-1, 1], not {config.min_similarity}")
    if config.max_landmarks is not None and config.max_landmarks < 1:
        raise InputError(f"max landmarks must be >= 1, not {config.max_landmarks}")
    if config.align and config.transform is not None:
        raise InputError("align and transform exclude each other")


def _similarity(transform) -> np.ndarray:
    """``transform`` as a 4x4 similarity matrix; InputError when it is not one."""
    T = np.asarray(transform, np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InputError(f"the transform must be a finite 4x4 matrix, got shape {T.shape}")
    det = float(np.linalg.det(T[:3, :3]))
    if det <= 0:
        raise InputError(f"the transform's 3x3 block is not a scaled rotation (determinant {det:.4g})")
    s = det ** (1 / 3)
    R = T[:3, :3] / s
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise InputError("the transform is not a similarity (s R | t)")
    return T


def moved_sequence(seq, transform):
    """``seq`` with its poses moved by the similarity ``transform`` (x_map = s R x_seq + t): each
    ``cam_from_world`` becomes ``cam_from_world @ transform^-1``, its rows scaled by s to stay rigid."""
    from ...geometry import move_poses

    T = _similarity(transform)
    moved = move_poses(np.stack([fr.cam_from_world for fr in seq.frames]), T)
    frames = [dataclasses.replace(fr, cam_from_world=P) for fr, P in zip(seq.frames, moved)]
    return dataclasses.replace(seq, frames=frames)


def camera_sequence(seq, cam_from_rig: np.ndarray):
    """``seq`` with the poses of the camera that the map's frames hold: ``cam_from_rig @ cam_from_world``
    (Map.cam_from_rig: the camera's rotation against the poses the map was built from)."""
    frames = [dataclasses.replace(fr, cam_from_world=cam_from_rig @ fr.cam_from_world) for fr in seq.frames]
    return dataclasses.replace(seq, frames=frames)


def _read_sequence(sequence, fmt):
    from ...io import Sequence, read_sequence

    if isinstance(sequence, Sequence):
        return sequence
    return read_sequence(sequence, fmt)


def extend_map(map_path, sequence, output, config: ExtendConfig | None = None, progress=None) -> ExtendSummary:
    """Add the posed frames of ``sequence`` (a folder, or a :class:`~favormap.io.Sequence`) to the map
    at ``map_path`` and write the result to ``output`` (atomically; ``output`` may not be the input).
    ``progress(stage, done, total)`` reports progress. See :mod:`favormap.ops.extend` for the steps."""
    from ...mapfile import Map
    from ...mapfile.writer import check_output_path
    from .pipeline import run_extension

    config = ExtendConfig() if config is None else config
    _check_config(config)
    map_path = Path(map_path)
    src = sequence if isinstance(sequence, (str, Path)) else None
    check_output_path(output, [map_path, src])  # before any work
    if not map_path.exists():
        raise InputError(f"map not found: {map_path}")
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    with Map.open(map_path) as mp:
        build_cfg = map_build_config(mp.provenance)
        seq = _read_sequence(sequence, config.format)  # a bad sequence fails before the map is read
        m = mp.load()
    timings["load"] = round(time.perf_counter() - t0, 3)
    transform, alignment = config.transform, None
    if config.align:
        t = time.perf_counter()
        alignment = _align(map_path, seq, build_cfg, config)
        transform = alignment["b_to_a"]
        timings["align"] = round(time.perf_counter() - t, 3)
    if transform is not None:
        seq = moved_sequence(seq, transform)
    if m.cam_from_rig is not None:  # the map's frames hold its camera's poses: the new frames' are turned alike
        seq = camera_sequence(seq, m.cam_from_rig)
    summary = run_extension(m, seq, Path(output), build_cfg, config, progress, timings)
    summary.transform = None if transform is None else np.asarray(transform, np.float64).tolist()
    summary.alignment = alignment
    if alignment is not None:
        summary.warnings += [f"alignment: {w}" for w in alignment["warnings"]]
    return summary


def _align(map_path: Path, seq, build_cfg, config: ExtendConfig) -> dict:
    """The similarity new_to_map from a quick map of ``seq`` aligned to the map (favormap.ops.align)."""
    from ...build import build_map
    from ...mapfile import write_map
    from ...voxels.config import VoxelConfig
    from ..align import align_maps

    quick = dataclasses.replace(build_cfg, voxel=VoxelConfig.preset("quick"), align_patches=0, refine_window=0)
    m = build_map(seq, quick, device=config.device)
    with tempfile.TemporaryDirectory(prefix="favormap-extend-") as tmp:
        path = Path(tmp) / "new.h5"
        write_map(m, path)
        return align_maps(map_path, path).to_dict()
