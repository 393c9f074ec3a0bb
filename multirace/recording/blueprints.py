"""The screens a replay opens on in rerun's viewer (blueprints), built where the replay is written.

The replay writer's process (`replay_writer`) builds them, so a race's own process never imports rerun.
`build(layout, ids, scalars, cameras)` gives the blueprint of a named layout: ``race`` (the 3D view, the
event log, every car's camera image or the race info, the plots) or ``explain`` (`multirace explain`: the
Grad-CAM overlay beside the camera).
"""
from __future__ import annotations

import rerun.blueprint as rrb


def _race_views(ids: list[str], plots: rrb.Tabs, cameras: bool) -> rrb.Vertical:
    if cameras:
        panel = rrb.Grid(*[rrb.Spatial2DView(origin=f"cameras/{car}", name=car) for car in ids], name="cameras")
    else:
        panel = rrb.TextDocumentView(origin="race/info")
    return rrb.Vertical(panel, plots, row_shares=[1, 1])


def _explain_views(ids: list[str], plots: rrb.Tabs, cameras: bool) -> rrb.Vertical:
    return rrb.Vertical(rrb.Spatial2DView(origin="explain", name="Grad-CAM"),
                        rrb.Spatial2DView(origin="cameras", name="camera"), plots)


LAYOUTS = {"race": _race_views, "explain": _explain_views}


def build(layout: str, ids: list[str], scalars: tuple, cameras: bool) -> rrb.Blueprint:
    """The blueprint of `layout` (a LAYOUTS name) for cars `ids` (entity names), the plots `scalars`, and
    `cameras` whether camera images are recorded."""
    plots = rrb.Tabs(*[rrb.TimeSeriesView(origin=f"plots/{name}", name=name) for name in scalars], name="plots")
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(rrb.Spatial3DView(origin="world", name="race"),
                         rrb.TextLogView(origin="events", name="events"), row_shares=[3, 1]),
            LAYOUTS[layout](ids, plots, cameras),
            column_shares=[3, 2]),
        rrb.TimePanel(timeline="race_time"),
        collapse_panels=True,
    )
