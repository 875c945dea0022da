"""Default viewer layouts (rerun blueprints) sent with each recording."""

from __future__ import annotations

import rerun.blueprint as rrb


def build_blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="map"),
            rrb.Vertical(
                rrb.Spatial2DView(origin="world/camera", name="frame (timeline: frame)"),
                rrb.Horizontal(
                    rrb.TimeSeriesView(origin="train/loss", name="loss (timeline: iteration)"),
                    rrb.TimeSeriesView(origin="train/psnr", name="PSNR dB (timeline: iteration)"),
                ),
                rrb.Horizontal(
                    rrb.TextDocumentView(origin="build/timings", name="timings"),
                    rrb.TextDocumentView(origin="build/stats", name="statistics"),
                ),
                row_shares=[3, 2, 2],
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline="frame"),
        collapse_panels=False,
    )


def localize_blueprint(methods: list[str], with_errors: bool) -> rrb.Blueprint:
    images = [rrb.Spatial2DView(origin=f"world/query/{m}/estimate", name=f"query ({m})") for m in methods]
    plots = [
        rrb.TimeSeriesView(origin="metrics/inliers", name="inliers"),
        rrb.TimeSeriesView(origin="metrics/similarity", name="match similarity"),
    ]
    if with_errors:
        plots = [
            rrb.TimeSeriesView(origin="metrics/translation_error", name="translation error"),
            rrb.TimeSeriesView(origin="metrics/rotation_error_deg", name="rotation error (deg)"),
        ] + plots
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="map & poses"),
            rrb.Vertical(
                images[0] if len(images) == 1 else rrb.Tabs(*images),
                rrb.Tabs(*plots, name="per query"),
                rrb.TextLogView(origin="log", name="log"),
                row_shares=[3, 2, 1],
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline="query"),
        collapse_panels=False,
    )


def map_blueprint(kind: str = "view") -> rrb.Blueprint:
    docs = [rrb.TextDocumentView(origin="map", contents="$origin", name="map info")]
    if kind == "merge":
        docs.append(rrb.TextDocumentView(origin="map/sources", name="sources"))
    elif kind == "prune":
        docs.append(rrb.TextDocumentView(origin="map/removed", name="pruned"))
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="map"),
            docs[0] if len(docs) == 1 else rrb.Vertical(*docs),
            column_shares=[4, 1],
        ),
        collapse_panels=False,
    )


def blueprint_for(kind: str, methods: list[str] | None = None) -> rrb.Blueprint:
    if kind == "build":
        return build_blueprint()
    if kind in ("localize", "eval", "query"):
        return localize_blueprint(methods or ["rendered"], with_errors=(kind == "eval"))
    return map_blueprint(kind)
