"""Candidate vantage positions, shared by both planners (men_spec 7.5): expected new area, overlap
share and
common stems with the best existing scan, the overlap rule (``overlap_rule``: common stems and/or
the thesis's
50 % overlap) and the planners' result :class:`VantagePlan` with its ``PROPOSAL_COLUMNS``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from forestmap_assets.core.exploration.frontier import OBSTACLE, UNMAPPED
from forestmap_assets.core.exploration.grid import ExplorationGrid
from forestmap_assets.core.exploration.visibility import (
    stem_visibility,
    visible_cells,
    visible_stems,
)
from forestmap_assets.params.men import ExplorationConfig

PROPOSAL_COLUMNS = [
    "rank",
    "x",
    "y",
    "ix",
    "iy",
    "expected_new_m2",
    "expected_gain_m2",
    "overlap_share",
    "common_stems",
    "reference_scan",
    "visible_stems",
    "incomplete_stems",
    "path_m",
    "score",
    "feasible",
    "source",
]


# ---- planning --------------------------------------------------------------------------------
@dataclass
class VantagePlan:
    """Result of :func:`plan_next_vantage`: ranked ``proposals`` (``PROPOSAL_COLUMNS``), the
    walking ``paths`` (rank -> (k, 2) xy) of the top proposals, the grid and its classes, the
    frontier mask, coverage figures, the current cell and (thesis strategy) the heading."""

    proposals: pd.DataFrame
    paths: dict[int, np.ndarray]
    grid: ExplorationGrid
    classes: np.ndarray
    frontier: np.ndarray
    coverage: dict
    current: tuple[int, int]
    heading: np.ndarray | None = None
    zone: int | None = None
    config: ExplorationConfig | None = None


def overlap_constraint(config: ExplorationConfig, common: np.ndarray, overlap: np.ndarray) -> np.ndarray:
    stems_ok = common >= config.min_common_stems
    area_ok = overlap >= config.min_overlap
    return {
        "stems": stems_ok,
        "area": area_ok,
        "either": stems_ok | area_ok,
        "both": stems_ok & area_ok,
    }[config.overlap_rule]


def evaluate_positions(
    grid: ExplorationGrid,
    classes: np.ndarray,
    positions: np.ndarray,
    stems: np.ndarray,
    scan_xy: np.ndarray,
    scan_ids: list[str],
    config: ExplorationConfig,
    incomplete: np.ndarray | None = None,
) -> pd.DataFrame:
    """Expected new area, overlap share, visible and common stems (best existing scan) of
    candidate positions (men_spec 7.5 overlap predictor, forest form); ``incomplete_stems``:
    visible stems among ``incomplete`` (mapped stems without a DBH yet)."""
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    occ = classes == OBSTACLE
    vis = visible_cells(
        grid,
        pos,
        occ,
        stems,
        radius_m=config.coverage_radius_m,
        blind_radius_m=config.blind_radius_m,
        n_rays=config.n_rays,
    )
    mapped = (classes != UNMAPPED).ravel()
    unmapped_plot = ((classes == UNMAPPED) & grid.in_plot).ravel()
    n_vis = vis.sum(axis=1)
    new_area = (vis & unmapped_plot).sum(axis=1) * grid.cell_m**2
    overlap = np.where(n_vis > 0, (vis & mapped).sum(axis=1) / np.maximum(n_vis, 1), 0.0)
    vs = visible_stems(pos, stems, **stem_visibility(config))
    if len(scan_xy) and len(stems):
        vscan = visible_stems(scan_xy, stems, **stem_visibility(config))
        common = vs.astype(np.int64) @ vscan.T.astype(np.int64)  # (n, scans)
        best = common.argmax(axis=1)
        n_common = common[np.arange(len(pos)), best]
        ref = np.asarray(scan_ids, dtype=object)[best]
    else:
        n_common = np.zeros(len(pos), dtype=np.int64)
        ref = np.full(len(pos), None, dtype=object)
    return pd.DataFrame(
        {
            "x": pos[:, 0],
            "y": pos[:, 1],
            "expected_new_m2": new_area,
            "overlap_share": overlap,
            "common_stems": n_common,
            "reference_scan": ref,
            "visible_stems": vs.sum(axis=1),
            "incomplete_stems": (vs & incomplete[None, :]).sum(axis=1)
            if incomplete is not None and len(incomplete) == vs.shape[1]
            else np.zeros(len(pos), dtype=np.int64),
        }
    )
