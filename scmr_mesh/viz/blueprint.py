"""The viewer layout, written in code (a rerun blueprint)."""

from __future__ import annotations

from collections.abc import Sequence

from scmr_mesh import keys
from scmr_mesh.viz.common import FAULTS, FLEET, ROBOT_ROOT


def fleet_blueprint(robots: Sequence[str]):
    """The viewer's layout: robot overlays in a grid, ToR and tier plots below.

    Returns a ``rerun.blueprint.Blueprint`` (imports rerun).
    """
    import rerun.blueprint as rrb

    robots = list(robots)
    overlays = [rrb.Spatial2DView(origin=f"{ROBOT_ROOT}/{r}/camera", name=r) for r in robots]
    if not overlays:
        overlays = [rrb.Spatial2DView(origin=ROBOT_ROOT, name="robots")]
    def per_robot(leaf: str) -> list[str]:
        if robots:
            return [f"{keys.RESULTS}/{r}/{leaf}" for r in robots]
        return [f"{keys.RESULTS}/**"]

    unit = rrb.ScalarAxis(range=(-0.1, 1.1))
    plots = rrb.Horizontal(
        rrb.TimeSeriesView(origin=keys.RESULTS, contents=per_robot("tor_ms"), name="ToR (ms)"),
        rrb.TimeSeriesView(
            origin=keys.RESULTS,
            contents=per_robot("tier"),
            name="tier (3 cloud, 2 leader, 1 peer, 0 local, -1 failed)",
            axis_y=rrb.ScalarAxis(range=(-1.3, 3.3)),
        ),
        rrb.Vertical(
            rrb.TimeSeriesView(origin=keys.ALIVE, name="alive (1 up, 0 gone)", axis_y=unit),
            rrb.TimeSeriesView(origin=FAULTS, name="faults (1 while on)", axis_y=unit),
        ),
        rrb.Vertical(
            rrb.TimeSeriesView(
                origin=keys.ROOT, contents=[f"{FLEET}/ror", *per_robot("ror")], name="RoR so far", axis_y=unit
            ),
            rrb.TextLogView(origin=keys.ROOT, name="events"),
        ),
        column_shares=[3, 3, 2, 2],
    )
    bp = rrb.Blueprint(
        rrb.Vertical(rrb.Grid(*overlays), plots, row_shares=[3, 2]),
        rrb.TimePanel(timeline="wall_time"),
        collapse_panels=False,
    )
    return bp
