"""The rerun recorder of every favormap command: the shared base (:mod:`.base`) with the build,
localize/eval and merge/prune logs (:mod:`.build_log`, :mod:`.localize_log`, :mod:`.ops_log`).

Timelines: ``frame`` (build: one step per mapping frame), ``iteration`` (build: voxel training),
``query`` (localize/eval: one step per query). Everything that does not change over time (map
landmarks, voxels, camera path, timings) is logged static. The entity paths are listed in
``docs/rerun.md``; keep the two in sync.
"""

from __future__ import annotations

from .base import RecordingBase, colormap, frustum_depth, frustum_segments, id_colors, markdown_table, view_coordinates
from .build_log import BuildLog
from .localize_log import LocalizeLog
from .ops_log import MapOpsLog
from .viewer import analytics_opt_in, rerun_executable, spawn_viewer, viewer_environment


class Recording(BuildLog, LocalizeLog, MapOpsLog, RecordingBase):
    """Logs what a favormap command does into one rerun recording.

    ``kind`` picks the default layout (build, localize, eval, view, merge, prune). Sinks: ``save``
    (an .rrd file), ``connect`` (a gRPC URL), ``spawn`` (start a local viewer); any combination."""


__all__ = [
    "Recording",
    "analytics_opt_in",
    "colormap",
    "frustum_depth",
    "frustum_segments",
    "id_colors",
    "markdown_table",
    "rerun_executable",
    "spawn_viewer",
    "view_coordinates",
    "viewer_environment",
]
