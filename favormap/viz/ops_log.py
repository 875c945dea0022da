"""The merge and prune recordings: the resulting map with where its landmarks came from or
which were removed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rerun as rr

from .base import (
    GREY,
    OUTLIER,
    RecordingBase,
    _guarded,
    id_colors,
    markdown_table,
)


class MapOpsLog(RecordingBase):
    """The maps that merge and prune write."""

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
            self.rec.log(
                "world/map/sources",
                rr.Points3D(
                    np.asarray(out.positions, np.float64),
                    colors=colors.astype(np.uint8),
                    radii=rr.Radius.ui_points(2.5),
                ),
                static=True,
            )
            rows.append(("regenerated ids", "", int((src < 0).sum())))
            self.rec.log(
                "map/sources",
                rr.TextDocument(
                    "### merged from\n\n" + markdown_table(rows, ("map", "landmarks", "in output")),
                    media_type=rr.MediaType.MARKDOWN,
                ),
                static=True,
            )

    @_guarded
    def log_prune(self, input_path, output_path) -> None:
        """The pruned map (as :meth:`log_map`) plus ``world/removed``: the landmarks pruning dropped."""
        from ..mapfile import Map

        with Map.open(output_path) as out, Map.open(input_path) as src:
            self.log_map(out)
            gone = ~np.isin(src.ids, out.ids)
            self.log_points("world/removed", np.asarray(src.positions)[gone], OUTLIER, 2.0)
            self.log_text(
                "map/removed",
                f"### pruned\n\nkept {len(out)} of {len(src)} landmarks, removed {int(gone.sum())} "
                "(red points in the 3D view: `world/removed`)",
            )
