"""Map completeness and the next vantage positions (Men 2012 ch. 3.7-3.8 and 6; men_spec 3.5-3.6,
7, 10), adapted to a forest surveyed on foot with a tripod scanner.

**Observed surface** (per scan, :func:`observed_surface`). Every return, plus samples along the
segment between two neighbouring returns of the organised image that no occlusion boundary
separates (:mod:`.occlusion`): the surface between them was swept by the beam, so at long
range, where the rings of ground hits lie farther apart than a grid cell, the ground between
them counts as seen (inferred). Voxelised at ``voxel_m`` in the levelled scan frame.

**Exploration grid** (:class:`ExplorationGrid`, men_spec 3.5). Square cells of ``cell_m`` over
the plot, each with a histogram of point heights in ``dz_m`` levels. The thesis measures height
from the first scanner (ground at -1.6 m, obstacles above -1.3 m); forest ground is uneven, so
heights here are relative to the *local ground* under each cell, taken from the merged lowest-
hit elevation map (:func:`local_ground`, men_spec 10). The thesis's flat index
``ix*N_y*N_z + iy*N_z + iz`` is kept (:meth:`ExplorationGrid.flat_index`).

**Classes** (:func:`classify_cells`, men_spec 3.6): O (obstacle) when at least
``min_obstacle_points`` lie between ``obstacle_min_m`` (0.3 m, thesis) and ``clearance_m``
above the local ground (points above it, canopy, are removed like the thesis's ceiling), or
the cell lies on a mapped stem; else G (ground) when a point lies below ``obstacle_min_m``;
else U (unmapped). Recomputed from the accumulated histogram, so a cell once O stays O (Eqs.
6.1-6.2). **Frontier** (men_spec 7.4): G cells of the plot 8-adjacent to a U cell of the plot.

**Next vantage positions** (:func:`plan_next_vantage`, men_spec 7.4-7.5). Candidates are
frontier cells, thinned to one per ``candidate_spacing_m`` block, reachable from the current
position by shortest paths over navigable cells (G cells, and the walked discs under the scan
positions, at least ``obstacle_clearance_m`` from an O cell: trees and dense understorey are
obstacles; 8-connected, Euclidean step costs, A* / Dijkstra). Each is scored with a 2-D
visibility model (:func:`visible_cells`: rays from the candidate up to ``coverage_radius_m``,
stopped by O cells and exactly by the mapped stems' discs, nothing seen inside the scanner's
blind disc ``blind_radius_m``): *expected new area* = visible unmapped plot cells, *overlap* =
share of visible cells already mapped (the thesis's 50 % rule), *predicted common stems* =
mapped stems visible both from the candidate and from the best existing scan
(:func:`visible_stems`: not hidden by nearer trunks and wide enough, at the scanner's angular
step, for the pipeline to find them). The overlap constraint (``overlap_rule``: at least
``min_common_stems`` common stems and/or ``min_overlap``) must hold; a frontier candidate that
fails it is moved back along its path to the farthest path position that passes (thesis 6.7
step 3). Feasible candidates are ranked by ``(new_area + stem_bonus_m2 x visible stems without a
DBH yet) * exp(-path_m / distance_scale_m)`` (inferred: the thesis never writes its cost
function). ``strategy="thesis"`` runs the thesis's
own lexicographic rule instead (:func:`thesis_next_vantage`: potential-field heading, 8 zones,
10 farthest frontier cells, best aligned, shrunk to 50 % overlap).
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field, fields
from typing import Literal

import numpy as np
import pandas as pd
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from forestmap_assets.core.features.elevation import ElevationGrid
from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.core.geometry import transform_points

UNMAPPED, GROUND, OBSTACLE = 0, 1, 2
CLASS_NAMES = ("unmapped", "ground", "obstacle")
SURFACE_COLUMNS = ["ix", "iy", "iz", "n_points", "n_filled"]
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


@dataclass(frozen=True)
class ExplorationConfig:
    """Parameters of the exploration grid and the planner (men_spec 7.8; forest values inferred).

    Thesis values: ``obstacle_min_m`` 0.3 m above the floor, ``min_overlap`` 0.5, ``n_proposals``
    10 candidates, 8 zones, ``coverage_radius_m`` 8 m indoors (15 m here: the range within which
    the pipeline finds stems), ``cell_m`` 0.2 m (0.25 m here). ``plot``: polygon vertices
    ``[[x, y], ...]`` in the global frame; None = the scan positions' bounding box grown by
    ``plot_margin_m``.
    """

    cell_m: float = 0.25
    height_min_m: float = -0.5
    height_max_m: float = 3.0
    dz_m: float = 0.1
    obstacle_min_m: float = 0.3
    clearance_m: float = 1.8
    min_ground_points: int = 1
    min_obstacle_points: int = 3
    ground_quantile: float = 0.25
    ground_window_m: float = 1.0
    map_range_m: float = 15.0
    coverage_radius_m: float = 15.0
    blind_radius_m: float = 1.8
    n_rays: int = 720
    stem_range_m: float = 15.0
    stem_visible_share: float = 0.5
    stem_min_pixels: float = 3.0
    angular_step_deg: float | None = None
    stem_margin_m: float = 0.05
    overlap_rule: Literal["stems", "area", "either", "both"] = "stems"
    min_common_stems: int = 5
    min_overlap: float = 0.5
    obstacle_clearance_m: float = 0.5
    candidate_spacing_m: float = 2.0
    min_scan_distance_m: float = 2.0
    path_step_m: float = 1.0
    distance_scale_m: float = 30.0
    stem_bonus_m2: float = 10.0
    n_proposals: int = 10
    strategy: Literal["coverage", "thesis"] = "coverage"
    zone_rule: Literal["heading", "unmapped"] = "heading"
    w_unmapped: float = 1.0
    w_wall: float = 1.0
    tangential_trigger_deg: float = 150.0
    min_density_per_m2: float = 100.0
    plot: tuple[tuple[float, float], ...] | None = None
    plot_margin_m: float = 10.0

    @classmethod
    def from_params(cls, section=None, **overrides) -> ExplorationConfig:
        """From a pydantic parameter section (or dict) with the same keys; unknown keys ignored."""
        values = section.model_dump() if hasattr(section, "model_dump") else dict(section or {})
        values.update(overrides)
        names = {f.name for f in fields(cls)}
        values = {k: v for k, v in values.items() if k in names}
        if values.get("plot") is not None:
            values["plot"] = tuple((float(x), float(y)) for x, y in values["plot"])
        return cls(**values)


# ---- observed surface (per scan) ----------------------------------------------------------------
def _segment_samples(p0: np.ndarray, p1: np.ndarray, step_m: float) -> np.ndarray:
    """Interior points every <= ``step_m`` along segments ``p0 -> p1`` (ends excluded)."""
    length = np.linalg.norm(p1 - p0, axis=1)
    k = np.maximum(np.ceil(length / step_m).astype(np.int64) - 1, 0)
    if k.sum() == 0:
        return np.zeros((0, 3))
    seg = np.repeat(np.arange(len(k)), k)
    start = np.cumsum(k) - k
    j = np.arange(k.sum()) - np.repeat(start, k) + 1
    t = (j / (k[seg] + 1))[:, None]
    return p0[seg] + t * (p1[seg] - p0[seg])


def observed_surface(
    image: RangeImage,
    tilt_pair: np.ndarray,
    pan_pair: np.ndarray,
    *,
    voxel_m: float = 0.05,
    fill_step_m: float = 0.1,
    max_fill_m: float = 2.0,
    wrap: bool = False,
) -> pd.DataFrame:
    """Voxelised observed surface of one scan in its levelled frame (``SURFACE_COLUMNS``).

    ``n_points``: returns in the voxel; ``n_filled``: samples every ``fill_step_m`` on segments
    between neighbouring returns (tilt and pan pairs) not flagged as occlusion boundaries and
    shorter than ``max_fill_m`` (inferred). ``tilt_pair`` / ``pan_pair`` are the flagged pair
    masks of :func:`~.occlusion.detect_occlusions`. Voxel ``(ix, iy, iz)`` covers
    ``[ix*voxel_m, (ix+1)*voxel_m)`` etc."""
    xyz = image.xyz
    valid = image.valid
    measured = xyz[valid]
    fills = []
    for axis, flagged in ((0, tilt_pair), (1, pan_pair)):
        if axis == 0:
            a, b, va, vb = xyz[:-1], xyz[1:], valid[:-1], valid[1:]
        elif wrap:
            a, b, va, vb = xyz, np.roll(xyz, -1, axis=1), valid, np.roll(valid, -1, axis=1)
        else:
            a, b, va, vb = xyz[:, :-1], xyz[:, 1:], valid[:, :-1], valid[:, 1:]
        ok = va & vb & ~flagged
        p0, p1 = a[ok], b[ok]
        length = np.linalg.norm(p1 - p0, axis=1)
        long = (length > fill_step_m) & (length <= max_fill_m)
        fills.append(_segment_samples(p0[long], p1[long], fill_step_m))
    filled = np.concatenate(fills) if fills else np.zeros((0, 3))
    pts = np.concatenate([measured, filled])
    is_fill = np.concatenate([np.zeros(len(measured), bool), np.ones(len(filled), bool)])
    if len(pts) == 0:
        return pd.DataFrame({c: pd.Series(dtype="int32") for c in SURFACE_COLUMNS})
    ijk = np.floor(pts / voxel_m).astype(np.int64)
    lo = ijk.min(axis=0)
    span = ijk.max(axis=0) - lo + 1
    key = ((ijk[:, 0] - lo[0]) * span[1] + (ijk[:, 1] - lo[1])) * span[2] + (ijk[:, 2] - lo[2])
    uniq, inv = np.unique(key, return_inverse=True)
    n_points = np.bincount(inv, weights=~is_fill, minlength=len(uniq)).astype(np.int32)
    n_filled = np.bincount(inv, weights=is_fill, minlength=len(uniq)).astype(np.int32)
    iz = uniq % span[2] + lo[2]
    rest = uniq // span[2]
    iy = rest % span[1] + lo[1]
    ix = rest // span[1] + lo[0]
    return pd.DataFrame(
        {
            "ix": ix.astype(np.int32),
            "iy": iy.astype(np.int32),
            "iz": iz.astype(np.int32),
            "n_points": n_points,
            "n_filled": n_filled,
        },
        columns=SURFACE_COLUMNS,
    )


def surface_points(
    surface: pd.DataFrame,
    voxel_m: float,
    pose=(0.0, 0.0, 0.0, 0.0),
    *,
    max_range_m: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Voxel centres of an observed surface in the global frame (``pose`` of the scan), with their
    ``n_points`` and ``n_filled``; voxels farther than ``max_range_m`` horizontally from the
    scanner are left out."""
    ijk = surface[["ix", "iy", "iz"]].to_numpy(np.float64)
    local = (ijk + 0.5) * voxel_m
    keep = (
        np.ones(len(local), bool)
        if max_range_m is None
        else np.hypot(local[:, 0], local[:, 1]) <= max_range_m
    )
    return (
        transform_points(local[keep], pose),
        surface["n_points"].to_numpy(np.float64)[keep],
        surface["n_filled"].to_numpy(np.float64)[keep],
    )


# ---- the exploration grid ----------------------------------------------------------------------
@dataclass
class ExplorationGrid:
    """2-D grid of ``cell_m`` cells with a height histogram per cell (men_spec 3.5).

    Arrays are indexed ``[ix, iy]`` (x first, as the thesis's flat index); cell ``(ix, iy)``
    covers ``[x0 + ix*cell_m, x0 + (ix+1)*cell_m) x [y0 + iy*cell_m, ...)``. Histogram level
    ``iz`` covers heights ``[z_min + iz*dz, z_min + (iz+1)*dz)``; heights are absolute ``z``
    (thesis) when ``ground_z`` is None, else ``z - ground_z[ix, iy]`` (forest, relative to the
    local ground). ``counts`` is the flat histogram ``Eg`` of every sample, ``measured`` the
    same of measured returns only (no gap-fill samples); ``points`` counts measured returns per
    cell at any height (density), ``above`` samples above the top level (canopy / ceiling)."""

    x0: float
    y0: float
    cell_m: float
    nx: int
    ny: int
    z_min: float
    dz: float
    nz: int
    ground_z: np.ndarray | None = None
    in_plot: np.ndarray | None = None
    polygon: np.ndarray | None = None
    counts: np.ndarray = field(default=None, repr=False)
    measured: np.ndarray = field(default=None, repr=False)
    points: np.ndarray = field(default=None, repr=False)
    above: np.ndarray = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.counts is None:
            self.counts = np.zeros(self.nx * self.ny * self.nz, dtype=np.float64)
        if self.measured is None:
            self.measured = np.zeros(self.nx * self.ny * self.nz, dtype=np.float64)
        if self.points is None:
            self.points = np.zeros((self.nx, self.ny), dtype=np.float64)
        if self.above is None:
            self.above = np.zeros((self.nx, self.ny), dtype=np.float64)
        if self.in_plot is None:
            self.in_plot = np.ones((self.nx, self.ny), dtype=bool)

    @classmethod
    def from_bounds(
        cls,
        bounds,
        cell_m: float,
        z_range: tuple[float, float],
        *,
        n_z: int | None = None,
        dz: float | None = None,
        plot=None,
    ) -> ExplorationGrid:
        """Grid over ``bounds = (x_min, x_max, y_min, y_max)`` (men_spec 3.5 initialisation:
        ``N_x = (x_max - x_min)/d_m``, ``d_z = (z_max - z_min)/N_z``); ``plot`` polygon marks the
        cells whose centre lies inside it."""
        x_min, x_max, y_min, y_max = (float(b) for b in bounds)
        nx = max(1, int(round((x_max - x_min) / cell_m)))
        ny = max(1, int(round((y_max - y_min) / cell_m)))
        z_lo, z_hi = (float(z) for z in z_range)
        if n_z is None:
            n_z = max(1, int(round((z_hi - z_lo) / dz)))
        grid = cls(x_min, y_min, float(cell_m), nx, ny, z_lo, (z_hi - z_lo) / n_z, int(n_z))
        if plot is not None:
            grid.in_plot = polygon_mask(grid, plot)
            grid.polygon = np.asarray(plot, dtype=np.float64).reshape(-1, 2)
        return grid

    @property
    def shape(self) -> tuple[int, int]:
        return (self.nx, self.ny)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        return (self.x0, self.x0 + self.nx * self.cell_m, self.y0, self.y0 + self.ny * self.cell_m)

    @property
    def hist(self) -> np.ndarray:
        """Height histogram (nx, ny, nz), a view of ``counts``."""
        return self.counts.reshape(self.nx, self.ny, self.nz)

    @property
    def measured_hist(self) -> np.ndarray:
        """Height histogram of measured returns only (nx, ny, nz)."""
        return self.measured.reshape(self.nx, self.ny, self.nz)

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre coordinates ``(x[ix], y[iy])``."""
        return (
            self.x0 + (np.arange(self.nx) + 0.5) * self.cell_m,
            self.y0 + (np.arange(self.ny) + 0.5) * self.cell_m,
        )

    def cell_xy(self, ix, iy) -> np.ndarray:
        return np.column_stack(
            [
                self.x0 + (np.asarray(ix) + 0.5) * self.cell_m,
                self.y0 + (np.asarray(iy) + 0.5) * self.cell_m,
            ]
        )

    def cell_of(self, x, y) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``ix, iy`` (floor, men_spec 3.5) and whether the point lies inside the grid."""
        ix = np.floor((np.asarray(x, dtype=np.float64) - self.x0) / self.cell_m).astype(np.int64)
        iy = np.floor((np.asarray(y, dtype=np.float64) - self.y0) / self.cell_m).astype(np.int64)
        inside = (ix >= 0) & (ix < self.nx) & (iy >= 0) & (iy < self.ny)
        return ix, iy, inside

    def heights(self, x, y, z) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``ix, iy``, height (absolute or above the local ground) and the inside mask."""
        ix, iy, inside = self.cell_of(x, y)
        h = np.asarray(z, dtype=np.float64).copy()
        if self.ground_z is not None:
            g = np.zeros(h.shape)
            g[inside] = self.ground_z[ix[inside], iy[inside]]
            h = h - g
        return ix, iy, h, inside

    def flat_index(self, x, y, z) -> tuple[np.ndarray, np.ndarray]:
        """Thesis update index ``ix*N_y*N_z + iy*N_z + iz`` and the mask of points inside B."""
        ix, iy, h, inside = self.heights(x, y, z)
        iz = np.floor((h - self.z_min) / self.dz).astype(np.int64)
        ok = inside & (iz >= 0) & (iz < self.nz)
        return np.where(ok, (ix * self.ny + iy) * self.nz + iz, -1), ok

    def add_points(
        self,
        points: np.ndarray,
        weights: np.ndarray | None = None,
        measured: np.ndarray | None = None,
    ) -> ExplorationGrid:
        """``Eg[flat_index] += weight`` for every point (men_spec 3.5 update), in place.

        ``measured``: the share of each weight that is measured returns (default: all of it),
        kept in ``measured`` and ``points``; points above the top level go to ``above``, points
        outside B or below the bottom level are dropped."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        w = np.ones(len(pts)) if weights is None else np.asarray(weights, dtype=np.float64)
        m = w if measured is None else np.asarray(measured, dtype=np.float64)
        idx, ok = self.flat_index(pts[:, 0], pts[:, 1], pts[:, 2])
        self.counts += np.bincount(idx[ok], weights=w[ok], minlength=self.counts.size)
        self.measured += np.bincount(idx[ok], weights=m[ok], minlength=self.counts.size)
        ix, iy, h, inside = self.heights(pts[:, 0], pts[:, 1], pts[:, 2])
        cell = ix * self.ny + iy
        top = inside & (h >= self.z_min + self.nz * self.dz)
        self.above += np.bincount(cell[top], weights=w[top], minlength=self.nx * self.ny).reshape(
            self.shape
        )
        self.points += np.bincount(
            cell[inside], weights=m[inside], minlength=self.nx * self.ny
        ).reshape(self.shape)
        return self


def polygon_mask(grid: ExplorationGrid, polygon) -> np.ndarray:
    """Cells whose centre lies inside ``polygon`` (vertices ``[[x, y], ...]``), (nx, ny)."""
    from matplotlib.path import Path as MplPath

    xc, yc = grid.centres()
    xx, yy = np.meshgrid(xc, yc, indexing="ij")
    inside = MplPath(np.asarray(polygon, dtype=np.float64)).contains_points(
        np.column_stack([xx.ravel(), yy.ravel()])
    )
    return inside.reshape(grid.shape)


def plot_bounds(
    config: ExplorationConfig, scan_xy: np.ndarray
) -> tuple[tuple[float, float, float, float], object]:
    """Grid bounds (snapped to whole cells) and plot polygon: ``config.plot`` or the scans'
    bounding box grown by ``plot_margin_m`` (inferred default)."""
    if config.plot is not None:
        poly = np.asarray(config.plot, dtype=np.float64)
    else:
        xy = np.asarray(scan_xy, dtype=np.float64).reshape(-1, 2)
        lo, hi = xy.min(axis=0) - config.plot_margin_m, xy.max(axis=0) + config.plot_margin_m
        poly = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    c = config.cell_m
    lo = np.floor(poly.min(axis=0) / c) * c
    hi = np.ceil(poly.max(axis=0) / c) * c
    return (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])), poly


def local_ground(
    elevation: ElevationGrid,
    grid: ExplorationGrid,
    *,
    quantile: float = 0.25,
    window_m: float = 1.0,
    default_z: float = 0.0,
) -> np.ndarray:
    """Ground height under every exploration cell (nx, ny) from the merged lowest-hit map.

    Per cell the median of the fine lowest-hit values inside it, then the ``quantile`` of those
    cell values over a ``2 window_m + cell`` square (a bush or stem cell whose lowest hit lies
    above the ground ranks high and takes the ground of its neighbours), cells without data take
    their nearest cell's value, and ``default_z`` when the map is empty (all inferred; men_spec
    10: heights relative to the local terrain)."""
    g0 = np.full(grid.shape, np.nan)
    z = elevation.z
    if z.size and np.isfinite(z).any():
        iy, ix = np.nonzero(np.isfinite(z))
        x = elevation.x0 + (ix + 0.5) * elevation.cell_m
        y = elevation.y0 + (iy + 0.5) * elevation.cell_m
        gx, gy, inside = grid.cell_of(x, y)
        key = (gx * grid.ny + gy)[inside]
        vals = z[iy, ix][inside]
        if key.size:
            order = np.lexsort((vals, key))
            key, vals = key[order], vals[order]
            uniq, start, count = np.unique(key, return_index=True, return_counts=True)
            lo, hi = start + (count - 1) // 2, start + count // 2
            g0.ravel()[uniq] = 0.5 * (vals[lo] + vals[hi])
    if not np.isfinite(g0).any():
        return np.full(grid.shape, float(default_z))
    k = max(1, int(round(window_m / grid.cell_m))) * 2 + 1
    g = ndimage.percentile_filter(
        np.where(np.isfinite(g0), g0, np.inf), 100 * quantile, size=k, mode="nearest"
    )
    g = np.where(np.isfinite(g), g, np.nan)
    missing = ~np.isfinite(g)
    if missing.any():
        _, (jx, jy) = ndimage.distance_transform_edt(missing, return_indices=True)
        g = g[jx, jy]
    return g


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


# ---- paths -----------------------------------------------------------------------------------
_STEPS = np.array([[1, 0], [0, 1], [1, 1], [1, -1]])


def navigable_cells(
    classes: np.ndarray,
    cell_m: float,
    *,
    obstacle_clearance_m: float = 0.5,
    walked: np.ndarray | None = None,
) -> np.ndarray:
    """Cells one may walk through (nx, ny): G cells and ``walked`` cells (the blind discs under the
    scan positions: the operator stood there) at least ``obstacle_clearance_m`` from any O cell
    (men_spec 3.6 robot footprint; inferred for a surveyor with a tripod)."""
    free = classes == GROUND
    if walked is not None:
        free |= walked & (classes != OBSTACLE)
    k = int(np.ceil(obstacle_clearance_m / cell_m - 1e-9))
    if k > 0:
        off = np.arange(-k, k + 1)
        disc = (
            np.hypot(*np.meshgrid(off, off, indexing="ij")) * cell_m <= obstacle_clearance_m + 1e-9
        )
        blocked = ndimage.binary_dilation(classes == OBSTACLE, structure=disc)
    else:
        blocked = classes == OBSTACLE
    return free & ~blocked


def grid_graph(nav: np.ndarray, cell_m: float) -> coo_matrix:
    """8-connected graph of navigable cells, Euclidean step costs; a diagonal step needs both
    orthogonal neighbours navigable (no corner cutting, inferred)."""
    nx, ny = nav.shape
    rows, cols, w = [], [], []
    for dx, dy in _STEPS:
        x0, x1 = max(0, -dx), nx - max(0, dx)
        y0, y1 = max(0, -dy), ny - max(0, dy)
        a = nav[x0:x1, y0:y1]
        b = nav[x0 + dx : x1 + dx, y0 + dy : y1 + dy]
        ok = a & b
        if dx and dy:
            ok &= nav[x0 + dx : x1 + dx, y0:y1] & nav[x0:x1, y0 + dy : y1 + dy]
        ia, ja = np.nonzero(ok)
        src = (ia + x0) * ny + (ja + y0)
        dst = (ia + x0 + dx) * ny + (ja + y0 + dy)
        rows += [src, dst]
        cols += [dst, src]
        w += [np.full(2 * src.size, cell_m * np.hypot(dx, dy))]
    n = nx * ny
    if not rows:
        return coo_matrix((n, n))
    return coo_matrix(
        (np.concatenate(w), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    )


def path_distances(
    nav: np.ndarray, start: tuple[int, int], cell_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Shortest walking distance (nx, ny; inf = unreachable) from ``start`` to every cell and the
    predecessor of each cell on its shortest path (-9999 none): Dijkstra, i.e. A* to every goal
    (men_spec 7.4)."""
    nav = nav.copy()
    nav[start] = True
    graph = grid_graph(nav, cell_m).tocsr()
    src = start[0] * nav.shape[1] + start[1]
    dist, pred = dijkstra(graph, directed=False, indices=src, return_predecessors=True)
    return dist.reshape(nav.shape), pred


def path_from(pred: np.ndarray, goal: tuple[int, int], shape: tuple[int, int]) -> np.ndarray:
    """Cells ``(k, 2)`` of the shortest path from the start to ``goal`` (from predecessors)."""
    ny = shape[1]
    node = int(goal[0]) * ny + int(goal[1])
    out = [node]
    while pred[node] >= 0:
        node = int(pred[node])
        out.append(node)
    out = np.array(out[::-1])
    return np.column_stack([out // ny, out % ny])


def astar(
    nav: np.ndarray, start: tuple[int, int], goal: tuple[int, int], cell_m: float = 1.0
) -> tuple[np.ndarray, float]:
    """A* path (cells ``(k, 2)``) and length over 8-connected navigable cells with the octile
    heuristic (men_spec 7.4-7.5); empty path and inf when the goal cannot be reached."""
    nx, ny = nav.shape
    nav = nav.copy()
    nav[start] = True
    goal = (int(goal[0]), int(goal[1]))
    if not nav[goal]:
        return np.zeros((0, 2), dtype=int), np.inf

    def h(c):
        dx, dy = abs(c[0] - goal[0]), abs(c[1] - goal[1])
        return cell_m * (max(dx, dy) + (np.sqrt(2) - 1) * min(dx, dy))

    start = (int(start[0]), int(start[1]))
    g = {start: 0.0}
    came: dict = {}
    heap = [(h(start), 0.0, start)]
    done = set()
    while heap:
        _, gc, c = heapq.heappop(heap)
        if c in done:
            continue
        if c == goal:
            path = [c]
            while c in came:
                c = came[c]
                path.append(c)
            return np.array(path[::-1]), gc
        done.add(c)
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                if not (dx or dy):
                    continue
                n = (c[0] + dx, c[1] + dy)
                if not (0 <= n[0] < nx and 0 <= n[1] < ny) or not nav[n] or n in done:
                    continue
                if dx and dy and not (nav[c[0] + dx, c[1]] and nav[c[0], c[1] + dy]):
                    continue
                ng = gc + cell_m * (np.sqrt(2) if dx and dy else 1.0)
                if ng < g.get(n, np.inf):
                    g[n] = ng
                    came[n] = c
                    heapq.heappush(heap, (ng + h(n), ng, n))
    return np.zeros((0, 2), dtype=int), np.inf


# ---- visibility ------------------------------------------------------------------------------
def _ray_circle_t(p: np.ndarray, u: np.ndarray, stems: np.ndarray) -> np.ndarray:
    """Distance along rays (n, m) from points ``p`` (n, 2) in directions ``u`` (m, 2) to the first
    stem disc hit (inf: none). ``stems`` rows ``x, y, r``."""
    if not len(stems):
        return np.full((len(p), len(u)), np.inf)
    rel = p[:, None, :] - stems[None, :, :2]  # (n, s, 2)
    b = np.einsum("nsk,mk->nms", rel, u)  # (n, m, s)
    c = (rel**2).sum(-1)[:, None, :] - stems[None, None, :, 2] ** 2
    disc = b * b - c
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(disc)
    t = np.where((disc >= 0) & (t > 0), t, np.inf)
    return t.min(axis=2)


def visible_cells(
    grid: ExplorationGrid,
    positions: np.ndarray,
    occluders: np.ndarray,
    stems: np.ndarray | None = None,
    *,
    radius_m: float = 15.0,
    blind_radius_m: float = 1.8,
    n_rays: int = 720,
    chunk: int = 16,
) -> np.ndarray:
    """2-D visibility model (men_spec 7.5 overlap predictor with visibility): cells (n, nx*ny)
    a scan at each position would see. Rays every ``360/n_rays`` deg are sampled every half cell
    from ``blind_radius_m`` (nothing below the scanner's lowest beam) to ``radius_m``; a ray stops
    at the first ``occluders`` cell (which is itself seen) and at the first stem disc
    (``stems`` rows ``x, y, r``, exact ray-circle intersection: trunk occlusion)."""
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    stems = (
        np.zeros((0, 3)) if stems is None else np.asarray(stems, dtype=np.float64).reshape(-1, 3)
    )
    theta = np.arange(n_rays) * (2 * np.pi / n_rays)
    u = np.column_stack([np.cos(theta), np.sin(theta)])
    t = np.arange(blind_radius_m, radius_m + 1e-9, 0.5 * grid.cell_m)
    occ = np.asarray(occluders, bool).ravel()
    out = np.zeros((len(pos), grid.nx * grid.ny), dtype=bool)
    for a in range(0, len(pos), chunk):
        p = pos[a : a + chunk]
        near = (
            stems[
                (
                    np.hypot(stems[:, 0:1] - p[None, :, 0], stems[:, 1:2] - p[None, :, 1]).min(
                        axis=1
                    )
                    <= radius_m + stems[:, 2]
                )
            ]
            if len(stems)
            else stems
        )
        t_stem = _ray_circle_t(p, u, near)  # (n, m)
        xy = p[:, None, None, :] + t[None, None, :, None] * u[None, :, None, :]  # (n, m, k, 2)
        ix, iy, inside = grid.cell_of(xy[..., 0], xy[..., 1])
        flat = np.where(inside, ix * grid.ny + iy, 0)
        blocked = inside & occ[flat]
        # samples after the first occluder sample are hidden; the occluder sample itself is seen
        hidden = np.cumsum(blocked, axis=2) - blocked > 0
        seen = inside & ~hidden & (t[None, None, :] < t_stem[:, :, None])
        rows = np.broadcast_to(np.arange(len(p))[:, None, None], seen.shape)
        out[a + rows[seen], flat[seen]] = True
    return out


def visible_stems(
    positions: np.ndarray,
    stems: np.ndarray,
    *,
    range_m: float = 15.0,
    min_share: float = 0.5,
    min_width_rad: float = 0.0,
    n_sub: int = 7,
) -> np.ndarray:
    """Which stems (``x, y, r`` rows) a scan at each position sees (n, s): within ``range_m``,
    at least ``min_width_rad`` wide as seen from there (enough pixels across the stem for the
    scan-line segments, see :func:`stem_visibility`), and at least ``min_share`` of its angular
    width not hidden by nearer stems (sampled with ``n_sub`` rays across the width; inferred)."""
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    stems = np.asarray(stems, dtype=np.float64).reshape(-1, 3)
    if not len(stems) or not len(pos):
        return np.zeros((len(pos), len(stems)), dtype=bool)
    if len(pos) > 8:  # chunks of positions, each with only the stems within range of it
        out = np.zeros((len(pos), len(stems)), dtype=bool)
        for a in range(0, len(pos), 8):
            p = pos[a : a + 8]
            dmin = np.hypot(
                stems[:, None, 0] - p[None, :, 0], stems[:, None, 1] - p[None, :, 1]
            ).min(axis=1)
            near = np.flatnonzero(dmin <= range_m + stems[:, 2])
            if len(near):
                out[a : a + 8, near] = visible_stems(
                    p,
                    stems[near],
                    range_m=range_m,
                    min_share=min_share,
                    min_width_rad=min_width_rad,
                    n_sub=n_sub,
                )
        return out
    d = pos[:, None, :] - stems[None, :, :2]
    dist = np.hypot(d[..., 0], d[..., 1])  # (n, s)
    bearing = np.arctan2(-d[..., 1], -d[..., 0])
    half = np.arcsin(np.clip(stems[None, :, 2] / np.maximum(dist, 1e-9), 0, 1))
    frac = (np.arange(n_sub) + 0.5) / n_sub * 2 - 1  # (-1, 1)
    ang = bearing[..., None] + 0.98 * half[..., None] * frac  # (n, s, k)
    u = np.stack([np.cos(ang), np.sin(ang)], -1)  # (n, s, k, 2)
    # distance along each sub-ray to every stem (n, s, k, s')
    rel = pos[:, None, None, None, :] - stems[None, None, None, :, :2]
    b = (rel * u[:, :, :, None, :]).sum(-1)
    c = (rel**2).sum(-1) - stems[None, None, None, :, 2] ** 2
    disc = b * b - c
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(disc)
    t = np.where((disc >= 0) & (t > 0), t, np.inf)
    own = np.arange(len(stems))
    t_own = t[:, own, :, own].transpose(1, 0, 2)  # (n, s, k)
    t[:, own, :, own] = np.inf
    clear = t.min(axis=3) >= t_own - 1e-9
    share = clear.mean(axis=2)
    wide = 2 * half >= min_width_rad
    return (dist <= range_m) & wide & (share >= min_share) & (dist > stems[None, :, 2])


def stem_visibility(config: ExplorationConfig) -> dict:
    """Keyword arguments of :func:`visible_stems` from the configuration: a stem counts when it
    spans at least ``stem_min_pixels`` columns of ``angular_step_deg`` (the scanner's azimuth
    step; no limit when None), so that the pipeline can find it (inferred: on simulated
    quarter-resolution scans stems about 3 columns wide or more got a cylinder, narrower ones
    mostly not)."""
    step = config.angular_step_deg
    return {
        "range_m": config.stem_range_m,
        "min_share": config.stem_visible_share,
        "min_width_rad": 0.0 if step is None else np.radians(step) * config.stem_min_pixels,
    }


# ---- thesis strategy: preferred heading, zones ---------------------------------------------
def preferred_heading(
    current: np.ndarray,
    unmapped_xy: np.ndarray,
    wall_xy: np.ndarray,
    diagonal: float,
    *,
    w_unmapped: float = 1.0,
    w_wall: float = 1.0,
    min_distance: float = 1e-6,
    tangential_trigger_deg: float = 150.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Potential-field heading (men_spec 7.2, Eqs. 6.3-6.7): ``H = W_u sum K_k u_k - W_w sum K_l
    u_l`` with ``K_k = |x_k - x_i|^2 / D^2`` and ``K_l = D^2 / |x_l - x_i|^2`` (distances clamped
    at ``min_distance``), plus the tangential force ``F_t = (F_w,y, -F_w,x)`` when the attractive
    and repulsive resultants point more than ``tangential_trigger_deg`` apart (inferred trigger).
    Returns ``(H, F_u, F_w)`` with ``F_w`` the repulsive resultant (pointing away from walls)."""
    cur = np.asarray(current, dtype=np.float64)

    def resultant(xy, attract):
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if not len(xy):
            return np.zeros(2)
        v = xy - cur
        d = np.maximum(np.hypot(v[:, 0], v[:, 1]), min_distance)
        unit = v / d[:, None]
        k = d**2 / diagonal**2 if attract else diagonal**2 / d**2
        return (k[:, None] * unit).sum(axis=0)

    f_u = w_unmapped * resultant(unmapped_xy, True)
    f_w = -w_wall * resultant(wall_xy, False)
    h = f_u + f_w
    nu, nw = np.linalg.norm(f_u), np.linalg.norm(f_w)
    if nu > 0 and nw > 0:
        angle = np.degrees(np.arccos(np.clip(f_u @ f_w / (nu * nw), -1, 1)))
        if angle > tangential_trigger_deg:
            h = h + np.array([f_w[1], -f_w[0]])
    return h, f_u, f_w


def zone_of(angles_rad: np.ndarray) -> np.ndarray:
    """Zone 0..7 of directions (45 deg sectors centred on 0, 45, ..., 315 deg; men_spec 7.3)."""
    a = np.mod(np.asarray(angles_rad, dtype=np.float64), 2 * np.pi)
    return (np.floor((a + np.pi / 8) / (np.pi / 4)).astype(int)) % 8


def _angle_diff(a, b):
    return np.abs((np.asarray(a) - b + np.pi) % (2 * np.pi) - np.pi)


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


def walked_cells(grid: ExplorationGrid, scan_xy: np.ndarray, radius_m: float) -> np.ndarray:
    """Cells within ``radius_m`` of a scan position (the blind disc under the scanner)."""
    xc, yc = grid.centres()
    out = np.zeros(grid.shape, dtype=bool)
    for x, y in np.asarray(scan_xy, dtype=np.float64).reshape(-1, 2):
        out |= np.hypot(xc[:, None] - x, yc[None, :] - y) <= radius_m
    return out


def build_grid(
    surfaces: list[tuple[pd.DataFrame, tuple, float]],
    elevation: ElevationGrid,
    scan_xy: np.ndarray,
    config: ExplorationConfig,
    *,
    default_ground_z: float = -1.5,
) -> ExplorationGrid:
    """Exploration grid of the plot from every registered scan's observed surface
    (``(table, pose, voxel_m)``) with heights above the local ground of ``elevation``."""
    bounds, poly = plot_bounds(config, scan_xy)
    grid = ExplorationGrid.from_bounds(
        bounds, config.cell_m, (config.height_min_m, config.height_max_m), dz=config.dz_m, plot=poly
    )
    grid.ground_z = local_ground(
        elevation,
        grid,
        quantile=config.ground_quantile,
        window_m=config.ground_window_m,
        default_z=default_ground_z,
    )
    for table, pose, voxel_m in surfaces:
        if table is None or not len(table):
            continue
        pts, n_pts, n_fill = surface_points(table, voxel_m, pose, max_range_m=config.map_range_m)
        grid.add_points(pts, n_pts + n_fill, measured=n_pts)
    return grid


def _constraint(config: ExplorationConfig, common: np.ndarray, overlap: np.ndarray) -> np.ndarray:
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
    ev["feasible"] = _constraint(
        config, ev["common_stems"].to_numpy(), ev["overlap_share"].to_numpy()
    )
    ev["expected_gain_m2"] = ev["expected_new_m2"] + config.stem_bonus_m2 * ev["incomplete_stems"]
    ev["score"] = ev["expected_gain_m2"] * np.exp(-ev["path_m"] / config.distance_scale_m)
    ev["source"] = source
    ev["rank"] = 0
    return ev



def _thesis_row(e, cell, dist: np.ndarray, feasible: bool, source: str) -> dict:
    """A proposal row of the thesis strategy (scored by expected new area alone) from the
    evaluation ``e`` of grid cell ``cell``; ``dist`` the walking distances."""
    return dict(
        x=e.x,
        y=e.y,
        ix=int(cell[0]),
        iy=int(cell[1]),
        expected_new_m2=e.expected_new_m2,
        expected_gain_m2=e.expected_new_m2,
        incomplete_stems=int(e.incomplete_stems),
        overlap_share=e.overlap_share,
        common_stems=int(e.common_stems),
        reference_scan=e.reference_scan,
        visible_stems=int(e.visible_stems),
        path_m=float(dist[cell[0], cell[1]]),
        score=float(e.expected_new_m2),
        feasible=feasible,
        source=source,
    )

def thesis_next_vantage(
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
    config: ExplorationConfig,
) -> VantagePlan:
    """The thesis's rule (men_spec 7.2-7.5, checklist 23-27): preferred heading H, its zone (or the
    zone with most unmapped cells), the 10 frontier cells of the zone farthest by path distance
    (2nd and 3rd kept as backups), the one best aligned with the principal direction, and on its
    A* path the farthest cell whose predicted overlap (visibility, coverage radius) passes the
    overlap rule (``area``: >= 50 %)."""
    xc, yc = grid.centres()
    cur_xy = grid.cell_xy(*current)[0]
    diag = float(np.hypot(grid.nx * grid.cell_m, grid.ny * grid.cell_m))
    unm = np.argwhere((classes == UNMAPPED) & grid.in_plot)
    wall = np.argwhere(classes == OBSTACLE)
    heading, _, _ = preferred_heading(
        cur_xy,
        grid.cell_xy(unm[:, 0], unm[:, 1]),
        grid.cell_xy(wall[:, 0], wall[:, 1]),
        diag,
        w_unmapped=config.w_unmapped,
        w_wall=config.w_wall,
        min_distance=grid.cell_m,
        tangential_trigger_deg=config.tangential_trigger_deg,
    )
    reach = frontier & np.isfinite(dist)
    fc = np.argwhere(reach)
    fz = (
        zone_of(np.arctan2(*(grid.cell_xy(fc[:, 0], fc[:, 1]) - cur_xy)[:, ::-1].T))
        if len(fc)
        else np.zeros(0, int)
    )
    uz = (
        zone_of(np.arctan2(*(grid.cell_xy(unm[:, 0], unm[:, 1]) - cur_xy)[:, ::-1].T))
        if len(unm)
        else np.zeros(0, int)
    )
    counts = np.bincount(uz, minlength=8)
    if config.zone_rule == "heading" and np.linalg.norm(heading) > 0:
        order = np.argsort(
            _angle_diff(np.arange(8) * np.pi / 4, np.arctan2(heading[1], heading[0]))
        )
    else:
        order = np.argsort(-counts, kind="stable")
    zone = None
    for z in order:  # fall back to the next zone when the selected one has no reachable frontier
        if (fz == z).any():
            zone = int(z)
            break
    rows = []
    paths: dict[int, np.ndarray] = {}
    if zone is not None:
        zc = fc[fz == zone]
        dz = dist[zc[:, 0], zc[:, 1]]
        top = zc[np.argsort(-dz, kind="stable")[: config.n_proposals]]
        principal = zone * np.pi / 4
        ang = np.arctan2(*(grid.cell_xy(top[:, 0], top[:, 1]) - cur_xy)[:, ::-1].T)
        pick = np.argsort(_angle_diff(ang, principal), kind="stable")
        chosen = top[pick[0]]
        path, _ = astar(nav, current, tuple(chosen), grid.cell_m)
        ev = evaluate_positions(
            grid, classes, grid.cell_xy(path[:, 0], path[:, 1]), stems, scan_xy, scan_ids, config
        )
        ok = _constraint(config, ev["common_stems"].to_numpy(), ev["overlap_share"].to_numpy())
        far = np.flatnonzero(ok)
        k = int(far.max()) if len(far) else 0
        sel = path[k]
        first = ev.iloc[k]
        rows.append(_thesis_row(first, sel, dist, bool(ok[k]), "thesis"))
        paths[1] = grid.cell_xy(path[: k + 1, 0], path[: k + 1, 1])
        # the other candidates (backups first), unshrunk, in the thesis's order of alignment
        rest = top[pick[1:]]
        if len(rest):
            ev2 = evaluate_positions(
                grid,
                classes,
                grid.cell_xy(rest[:, 0], rest[:, 1]),
                stems,
                scan_xy,
                scan_ids,
                config,
            )
            ok2 = _constraint(
                config, ev2["common_stems"].to_numpy(), ev2["overlap_share"].to_numpy()
            )
            for j, (c, e) in enumerate(zip(rest, ev2.itertuples(), strict=True)):
                rows.append(_thesis_row(e, c, dist, bool(ok2[j]), "backup" if j < 2 else "candidate"))
    table = pd.DataFrame(rows, columns=[c for c in PROPOSAL_COLUMNS if c != "rank"])
    table.insert(0, "rank", np.arange(1, len(table) + 1))
    return VantagePlan(
        table[PROPOSAL_COLUMNS],
        paths,
        grid,
        classes,
        frontier,
        coverage,
        current,
        heading=heading,
        zone=zone,
        config=config,
    )


# ---- picture ---------------------------------------------------------------------------------
def exploration_figure(
    plan: VantagePlan,
    elevation: ElevationGrid | None = None,
    stems: np.ndarray | None = None,
    scans: pd.DataFrame | None = None,
    *,
    title: str = "next vantage positions",
    n_show: int = 5,
):
    """Picture: elevation map, unmapped / obstacle cells, stems, scan positions, frontier,
    proposals (numbered by rank) and the walking paths to them (a matplotlib Figure)."""
    from matplotlib.colors import ListedColormap
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle

    grid = plan.grid
    fig = Figure(figsize=(8.0, 7.0))
    ax = fig.add_subplot(1, 1, 1)
    if elevation is not None and elevation.z.size and np.isfinite(elevation.z).any():
        # colours span the local ground of the plot (lowest hits in the canopy are clipped)
        if grid.ground_z is not None:
            lo, hi = (
                np.nanpercentile(grid.ground_z[grid.in_plot], [0.5, 99.5])
                if grid.in_plot.any()
                else (0, 1)
            )
            hi += max(0.5, 0.2 * (hi - lo))
        else:
            lo, hi = np.nanpercentile(elevation.z, [1, 90])
        im = ax.imshow(
            np.ma.masked_invalid(elevation.z),
            origin="lower",
            extent=elevation.extent,
            cmap="terrain",
            interpolation="nearest",
            alpha=0.9,
            vmin=lo,
            vmax=hi,
        )
        fig.colorbar(im, ax=ax, shrink=0.8, label="lowest hit (m)", extend="max")
    cls = np.where(grid.in_plot, plan.classes, 255).T
    overlay = np.ma.masked_where((cls != UNMAPPED) & (cls != OBSTACLE), cls)
    ax.imshow(
        overlay,
        origin="lower",
        extent=grid.extent,
        interpolation="nearest",
        cmap=ListedColormap(["#d9d9d9", "#d9d9d9", "#404040"]),
        vmin=0,
        vmax=2,
        alpha=0.75,
    )
    x0, x1, y0, y1 = grid.extent
    if grid.polygon is not None:
        poly = np.vstack([grid.polygon, grid.polygon[:1]])
        ax.plot(poly[:, 0], poly[:, 1], color="black", lw=0.8, label="plot")
    fr = np.argwhere(plan.frontier)
    if len(fr):
        fxy = grid.cell_xy(fr[:, 0], fr[:, 1])
        ax.scatter(
            fxy[:, 0], fxy[:, 1], s=1.5, c="orange", marker="s", linewidths=0, label="frontier"
        )
    if stems is not None and len(stems):
        st = np.asarray(stems, dtype=np.float64).reshape(-1, 3)
        for x, y, r in st:
            ax.add_patch(Circle((x, y), r, facecolor="saddlebrown", edgecolor="none"))
        ax.scatter(
            st[:, 0],
            st[:, 1],
            s=14,
            marker="o",
            facecolors="none",
            edgecolors="saddlebrown",
            linewidths=0.9,
            label="stems",
        )
    for rank, path in sorted(plan.paths.items())[:n_show]:
        ax.plot(
            path[:, 0],
            path[:, 1],
            color="blue" if rank == 1 else "steelblue",
            lw=1.6 if rank == 1 else 0.8,
            alpha=0.9 if rank == 1 else 0.6,
        )
    top = plan.proposals.head(n_show)
    if len(top):
        ax.scatter(
            top["x"],
            top["y"],
            s=90,
            marker="*",
            c=np.where(top["feasible"], "blue", "red"),
            edgecolors="white",
            linewidths=0.6,
            zorder=5,
            label="proposals",
        )
        for r in top.itertuples():
            ax.annotate(
                str(r.rank),
                (r.x, r.y),
                xytext=(5, 5),
                textcoords="offset points",
                fontsize=8,
                color="navy",
                weight="bold",
            )
    if scans is not None and len(scans):
        ax.scatter(
            scans["x"], scans["y"], s=45, c="red", edgecolors="black", zorder=6, label="scans"
        )
        if "scan" in scans:
            for r in scans.itertuples():
                ax.annotate(
                    str(r.scan),
                    (r.x, r.y),
                    xytext=(5, -11),
                    textcoords="offset points",
                    fontsize=8,
                    weight="bold",
                    bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.7},
                )
    cov = plan.coverage
    ax.set_title(
        f"{title}\ncoverage {100 * cov['coverage']:.1f} % of the plot, "
        f"{int(plan.frontier.sum())} frontier cells",
        fontsize=10,
    )
    ax.set_xlim(x0 - 1, x1 + 1)
    ax.set_ylim(y0 - 1, y1 + 1)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="upper right", fontsize=7, markerscale=1.0)
    fig.tight_layout()
    return fig
