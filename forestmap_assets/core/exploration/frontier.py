"""Cell classes, frontier and completeness (men_spec 3.6, 7.1, 7.4; Eqs. 6.1-6.2): O (obstacle) from
measured
returns between ``obstacle_min_m`` and ``clearance_m`` above the local ground or a mapped stem disc,
G (ground)
from samples below ``obstacle_min_m``, else U; frontier = G plot cells 8-adjacent to a U plot cell;
coverage figures."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from forestmap_assets.core.exploration.grid import ExplorationGrid

UNMAPPED, GROUND, OBSTACLE = 0, 1, 2


CLASS_NAMES = ("unmapped", "ground", "obstacle")


def stem_cells(grid: ExplorationGrid, stems: np.ndarray, margin_m: float = 0.05) -> np.ndarray:
    """Cells (nx, ny) a stem disc (``x, y, r`` rows) covers (centre within r + cell/2 + margin)."""
    out = np.zeros(grid.shape, dtype=bool)
    stems = np.asarray(stems, dtype=np.float64).reshape(-1, 3)
    if not len(stems):
        return out
    xc, yc = grid.centres()
    reach = stems[:, 2] + 0.5 * grid.cell_m + margin_m
    k = int(np.ceil(reach.max() / grid.cell_m)) + 1
    off = np.arange(-k, k + 1)
    ox, oy = (a.ravel() for a in np.meshgrid(off, off, indexing="ij"))
    ix0, iy0, _ = grid.cell_of(stems[:, 0], stems[:, 1])
    ix = ix0[:, None] + ox[None]
    iy = iy0[:, None] + oy[None]
    ok = (ix >= 0) & (ix < grid.nx) & (iy >= 0) & (iy < grid.ny)
    ixc, iyc = np.clip(ix, 0, grid.nx - 1), np.clip(iy, 0, grid.ny - 1)
    d = np.hypot(xc[ixc] - stems[:, :1], yc[iyc] - stems[:, 1:2])
    hit = ok & (d <= reach[:, None])
    out[ix[hit], iy[hit]] = True
    return out


def classify_cells(
    grid: ExplorationGrid,
    *,
    obstacle_min_m: float = 0.3,
    clearance_m: float = 1.8,
    min_ground_points: float = 1,
    min_obstacle_points: float = 3,
    stems: np.ndarray | None = None,
    stem_margin_m: float = 0.05,
) -> np.ndarray:
    """U / G / O class of every cell (nx, ny), men_spec 3.6 with heights from the grid's levels.

    O: at least ``min_obstacle_points`` measured returns in levels between ``obstacle_min_m`` and
    ``clearance_m`` (thesis 0.3 m above the floor; the clearance removes canopy as the thesis
    removes the ceiling; gap-fill samples are no evidence of an obstacle), or on a stem disc;
    G: at least ``min_ground_points`` samples below ``obstacle_min_m``; U: otherwise."""
    lo_edges = grid.z_min + np.arange(grid.nz) * grid.dz
    ground_levels = lo_edges + grid.dz <= obstacle_min_m + 1e-9
    obstacle_levels = (lo_edges >= obstacle_min_m - 1e-9) & (lo_edges < clearance_m - 1e-9)
    ground = grid.hist[:, :, ground_levels].sum(axis=2)
    obstacle = grid.measured_hist[:, :, obstacle_levels].sum(axis=2)
    classes = np.full(grid.shape, UNMAPPED, dtype=np.uint8)
    classes[ground >= min_ground_points] = GROUND
    classes[obstacle >= min_obstacle_points] = OBSTACLE
    if stems is not None and len(stems):
        classes[stem_cells(grid, stems, stem_margin_m)] = OBSTACLE
    return classes


_NEIGHBOURS8 = np.ones((3, 3), dtype=bool)


def frontier_cells(classes: np.ndarray, in_plot: np.ndarray | None = None) -> np.ndarray:
    """G cells (of the plot) 8-adjacent to at least one U cell of the plot (men_spec 7.4)."""
    plot = np.ones(classes.shape, bool) if in_plot is None else in_plot
    unmapped = (classes == UNMAPPED) & plot
    near_u = ndimage.binary_dilation(unmapped, structure=_NEIGHBOURS8)
    return (classes == GROUND) & plot & near_u


def coverage_figures(
    grid: ExplorationGrid, classes: np.ndarray, *, min_density_per_m2: float = 100.0
) -> dict:
    """Completeness of the plot (men_spec 7.1): shares of plot cells mapped (G or O), ground,
    obstacle, unmapped; measured points per m^2 over mapped cells (median, 10th percentile) and
    the share of plot cells with at least ``min_density_per_m2``."""
    plot = grid.in_plot
    n = max(int(plot.sum()), 1)
    area = grid.cell_m**2
    mapped = (classes != UNMAPPED) & plot
    density = grid.points / area
    dens = density[mapped]
    return {
        "plot_cells": int(plot.sum()),
        "plot_area_m2": round(float(plot.sum() * area), 2),
        "coverage": round(float(mapped.sum() / n), 4),
        "ground_share": round(float(((classes == GROUND) & plot).sum() / n), 4),
        "obstacle_share": round(float(((classes == OBSTACLE) & plot).sum() / n), 4),
        "unmapped_share": round(float(((classes == UNMAPPED) & plot).sum() / n), 4),
        "mapped_area_m2": round(float(mapped.sum() * area), 2),
        "median_points_per_m2": round(float(np.median(dens)), 1) if dens.size else 0.0,
        "p10_points_per_m2": round(float(np.percentile(dens, 10)), 1) if dens.size else 0.0,
        "dense_share": round(float(((density >= min_density_per_m2) & plot).sum() / n), 4),
    }
