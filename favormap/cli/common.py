"""Helpers shared by the subcommands."""

from __future__ import annotations

import dataclasses
import json
import sys


def config_default(cls, name: str):
    """The default of field ``name`` of the dataclass ``cls``: each option's default is read from the
    settings it fills in, so that a changed default changes the CLI too."""
    f = next(f for f in dataclasses.fields(cls) if f.name == name)
    return f.default_factory() if f.default is dataclasses.MISSING else f.default


def _gpu_driver_present() -> bool:
    """An NVIDIA (or ROCm) driver is installed: without one torch cannot see a GPU, and "auto"
    resolves to the CPU without importing torch (~2 s)."""
    import glob
    import os

    return (
        os.path.exists("/proc/driver/nvidia/version")
        or bool(glob.glob("/dev/nvidia[0-9]*"))
        or os.path.exists("/dev/kfd")
    )


def auto_device(name: str | None) -> str:
    if name in (None, "auto") and not _gpu_driver_present():
        return "cpu"
    if name == "cpu":
        return name
    import torch

    if name in (None, "auto"):
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        from ..errors import InputError

        raise InputError("--device cuda requested but no CUDA device is available")
    return name


def print_json(obj) -> None:
    import numpy as np

    def default(o):
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
        return str(o)

    sys.stdout.write(json.dumps(obj, default=default) + "\n")


def human_size(n: int) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n} B"


class StageBars:
    """One tqdm progress bar per pipeline stage (on stderr); silent when ``quiet``."""

    def __init__(self, quiet: bool = False):
        # bars only on a terminal: piped/logged stderr gets nothing but a final error line
        self.quiet = quiet or not sys.stderr.isatty()
        self.bars = {}

    def __call__(self, stage: str, done: int, total: int):
        if self.quiet:
            return
        from tqdm import tqdm

        bar = self.bars.get(stage)
        if bar is None:
            for b in self.bars.values():
                b.close()
            bar = self.bars[stage] = tqdm(
                total=total,
                desc=f"{stage:<12}",
                unit="",
                leave=True,
                file=sys.stderr,
                bar_format="{desc} {bar:30} {n_fmt}/{total_fmt} [{elapsed}]",
            )
        bar.n = done
        bar.refresh()

    def close(self):
        for b in self.bars.values():
            b.close()
        self.bars = {}


def estimated_poses_line(poses: dict, units: bool = True) -> str:
    """The one wording of a map's estimated poses and their units (build summary and info; ``units`` False:
    an extension's, in the map's units)."""
    line = f"poses               estimated from the images ({poses['mapper']} mapper, {poses['matcher']} matching)"
    if not units:
        return line + "; moved into the map's frame by the alignment"
    if poses.get("units") == "anchors":
        a = poses.get("anchors") or {}
        return line + (
            f"; units: metres, in the frame of {a.get('anchors', '?')} anchor poses (scale {poses['scale']:.6g}, "
            f"camera centres off by {a.get('residual_rms', float('nan')):.3g} m RMS)"
        )
    if poses.get("units") == "scaled":
        return line + f"; units: the reconstruction's times {poses['scale']:g}"
    return line + "; units arbitrary (no metric scale: --scale or --anchor-poses sets one)"


def reproj_error_line(px: float) -> str:
    """The one wording of the map's reprojection-error figure (build summary and info)."""
    return f"median reproj error {px:.3f} px  (landmarks of 3 or more views, each the mean over its observations)"


def voxel_memory_line(mem: int) -> str:
    """The line of ``favormap info`` and the build summary on the memory a warm localizer's voxel cache takes."""
    from ..mapfile.reader import DEFAULT_CACHE_BYTES

    return f"voxel memory        {human_size(mem)} for every grid: a warm localizer " + (
        f"holds them all (default cache {human_size(DEFAULT_CACHE_BYTES)})"
        if mem <= DEFAULT_CACHE_BYTES
        else "reads them as queries need them (localize --cache-mb)"
    )
