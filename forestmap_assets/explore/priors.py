"""A priori alignment of a new scan (inferred, men_spec 7.7): the planned position with the local
ground + 1.5 m and a compass heading, relative to a reference scan's estimated pose; further
references are registered scans predicted to share enough stems with the position."""

from __future__ import annotations

import numpy as np

from forestmap_assets.explore.survey_map import SurveyMap
from forestmap_assets.params.men import ExplorationConfig
from forestmap_assets.sim.campaign import wrap_deg


def prior_pose(xy_global, ground_z: float, heading_global: float, height_m: float = 1.5) -> tuple:
    return (
        float(xy_global[0]),
        float(xy_global[1]),
        float(ground_z) + height_m,
        float(wrap_deg(heading_global)),
    )


def relative_pose_tuple(scan_pose, reference_pose) -> tuple:
    from forestmap_assets.core.geometry import relative_pose as rel

    return rel(scan_pose, reference_pose)


def ground_at(grid, xy) -> float:
    ix, iy, inside = grid.cell_of(xy[0], xy[1])
    if grid.ground_z is None or not inside:
        return float(np.nanmedian(grid.ground_z)) if grid.ground_z is not None else -1.5
    return float(grid.ground_z[ix, iy])


def more_references(sm: SurveyMap, xy, first: str, config: ExplorationConfig, n: int) -> list[str]:
    """Up to ``n`` further registered scans predicted to share enough stems with position ``xy``."""
    from forestmap_assets.core.exploration.visibility import stem_visibility, visible_stems

    if n <= 0 or len(sm.scans) < 2 or not len(sm.stems):
        return []
    kw = stem_visibility(sm.plan.config) if sm.plan.config is not None else stem_visibility(config)
    vs = visible_stems(np.asarray(xy)[None], sm.stems, **kw)
    vscan = visible_stems(sm.scans[["x", "y"]].to_numpy(float), sm.stems, **kw)
    common = (vscan & vs).sum(axis=1)
    order = np.argsort(-common, kind="stable")
    ids = sm.scans["scan"].astype(str).to_numpy()
    return [ids[i] for i in order if ids[i] != first and common[i] >= config.min_common_stems][:n]
