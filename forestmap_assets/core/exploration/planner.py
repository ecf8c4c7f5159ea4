"""Next vantage positions (men_spec 7.4-7.5, thesis 6.7): classes, frontier and paths, then the
coverage strategy:
frontier cells thinned to one per ``candidate_spacing_m``, ranked by ``(new_area + stem_bonus_m2 x
stems without a
DBH) * exp(-path_m / distance_scale_m)`` (inferred), infeasible ones moved back along their paths
(thesis 6.7 step 3)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.core.exploration.candidates import (
    PROPOSAL_COLUMNS,
    VantagePlan,
    evaluate_positions,
    overlap_constraint,
)
from forestmap_assets.core.exploration.frontier import (
    classify_cells,
    coverage_figures,
    frontier_cells,
)
from forestmap_assets.core.exploration.grid import ExplorationGrid
from forestmap_assets.core.exploration.paths import (
    navigable_cells,
    path_distances,
    path_from,
    walked_cells,
)
from forestmap_assets.core.exploration.planner_thesis import thesis_next_vantage
from forestmap_assets.params.men import ExplorationConfig


def _thin(cells: np.ndarray, grid: ExplorationGrid, spacing_m: float) -> np.ndarray:
    """One cell per ``spacing_m`` block: the one nearest the block's mean (cells (k, 2))."""
    if not len(cells):
        return cells
    b = np.floor(cells * grid.cell_m / spacing_m).astype(np.int64)
    key = b[:, 0] * 1_000_003 + b[:, 1]
    uniq, inv = np.unique(key, return_inverse=True)
    mean = np.stack([np.bincount(inv, cells[:, k]) for k in (0, 1)], 1) / np.bincount(inv)[:, None]
    d = np.hypot(*(cells - mean[inv]).T)
    order = np.lexsort((d, inv))
    first = np.unique(inv[order], return_index=True)[1]
    return cells[order[first]]


def plan_next_vantage(
    grid: ExplorationGrid,
    stems: np.ndarray,
    scan_xy: np.ndarray,
    scan_ids: list[str],
    config: ExplorationConfig,
    *,
    current_xy: np.ndarray | None = None,
    incomplete: np.ndarray | None = None,
) -> VantagePlan:
    """Classes, frontier, coverage and the ranked next vantage positions (module docstring).

    ``stems``: mapped stems ``x, y, r`` (global); ``scan_xy``: registered scan positions;
    ``current_xy``: where the surveyor stands (default: the last scan); ``incomplete``: per
    stem, True when it has no DBH yet (each one a candidate sees adds ``stem_bonus_m2`` to its
    expected gain, inferred: area alone does not ask for a second look at a half-seen stem)."""
    stems = np.asarray(stems, dtype=np.float64).reshape(-1, 3)
    scan_xy = np.asarray(scan_xy, dtype=np.float64).reshape(-1, 2)
    classes = classify_cells(
        grid,
        obstacle_min_m=config.obstacle_min_m,
        clearance_m=config.clearance_m,
        min_ground_points=config.min_ground_points,
        min_obstacle_points=config.min_obstacle_points,
        stems=stems,
        stem_margin_m=config.stem_margin_m,
    )
    frontier = frontier_cells(classes, grid.in_plot)
    coverage = coverage_figures(grid, classes, min_density_per_m2=config.min_density_per_m2)
    if current_xy is not None:
        cur_xy = np.asarray(current_xy, dtype=np.float64)
    else:
        cur_xy = scan_xy[-1] if len(scan_xy) else np.zeros(2)
    cx, cy, _ = grid.cell_of(cur_xy[0], cur_xy[1])
    current = (int(np.clip(cx, 0, grid.nx - 1)), int(np.clip(cy, 0, grid.ny - 1)))
    walked = walked_cells(grid, scan_xy, config.blind_radius_m)
    nav = navigable_cells(
        classes, grid.cell_m, obstacle_clearance_m=config.obstacle_clearance_m, walked=walked
    )
    dist, pred = path_distances(nav, current, grid.cell_m)
    if config.strategy == "thesis":
        return thesis_next_vantage(
            grid,
            classes,
            frontier,
            coverage,
            nav,
            dist,
            pred,
            current,
            stems,
            scan_xy,
            scan_ids,
            config,
        )

    far_from_scans = np.ones(grid.shape, bool)
    if len(scan_xy):
        xc, yc = grid.centres()
        dmin = np.full(grid.shape, np.inf)
        for x, y in scan_xy:
            dmin = np.minimum(dmin, np.hypot(xc[:, None] - x, yc[None, :] - y))
        far_from_scans = dmin >= config.min_scan_distance_m
    ok = frontier & nav & np.isfinite(dist) & far_from_scans & grid.in_plot
    cells = _thin(np.argwhere(ok), grid, config.candidate_spacing_m)
    table = _score(
        grid, classes, cells, dist, stems, scan_xy, scan_ids, config, "frontier", incomplete
    )
    # thesis 6.7 step 3: move infeasible promising frontier candidates back along their paths
    bad = table[~table["feasible"]].nlargest(config.n_proposals, "expected_gain_m2")
    step = max(1, int(round(config.path_step_m / grid.cell_m)))
    extra, owner = [], []
    for k, r in enumerate(bad.itertuples()):
        back = path_from(pred, (r.ix, r.iy), grid.shape)[::-1][step::step]  # from the far end back
        back = back[far_from_scans[back[:, 0], back[:, 1]]] if len(back) else back
        extra.append(back)
        owner.append(np.full(len(back), k))
    if extra and sum(map(len, extra)):
        cells2 = np.concatenate(extra)
        t2 = _score(
            grid, classes, cells2, dist, stems, scan_xy, scan_ids, config, "path", incomplete
        )
        t2["owner"] = np.concatenate(owner)
        # per frontier candidate, the farthest feasible position on its path (first going back)
        t2 = t2[t2["feasible"]].groupby("owner", sort=False).head(1).drop(columns="owner")
        table = pd.concat([table, t2], ignore_index=True).drop_duplicates(["ix", "iy"])
    table = table.sort_values(
        ["feasible", "score", "expected_new_m2"], ascending=[False, False, False]
    )
    table = table.reset_index(drop=True)
    table["rank"] = np.arange(1, len(table) + 1)
    table = table[PROPOSAL_COLUMNS]
    paths = {}
    for r in table.head(config.n_proposals).itertuples():
        cells_p = path_from(pred, (r.ix, r.iy), grid.shape)
        paths[int(r.rank)] = grid.cell_xy(cells_p[:, 0], cells_p[:, 1])
    return VantagePlan(table, paths, grid, classes, frontier, coverage, current, config=config)


def _score(
    grid, classes, cells, dist, stems, scan_xy, scan_ids, config, source, incomplete=None
) -> pd.DataFrame:
    """Evaluate candidate cells: feasibility and ``score = (new area + stem_bonus_m2 x visible
    incomplete stems) x exp(-path / distance_scale_m)``."""
    cells = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
    xy = grid.cell_xy(cells[:, 0], cells[:, 1])
    ev = evaluate_positions(grid, classes, xy, stems, scan_xy, scan_ids, config, incomplete)
    ev["ix"], ev["iy"] = cells[:, 0], cells[:, 1]
    ev["path_m"] = dist[cells[:, 0], cells[:, 1]] if len(cells) else np.zeros(0)
    ev["feasible"] = overlap_constraint(
        config, ev["common_stems"].to_numpy(), ev["overlap_share"].to_numpy()
    )
    ev["expected_gain_m2"] = ev["expected_new_m2"] + config.stem_bonus_m2 * ev["incomplete_stems"]
    ev["score"] = ev["expected_gain_m2"] * np.exp(-ev["path_m"] / config.distance_scale_m)
    ev["source"] = source
    ev["rank"] = 0
    return ev
