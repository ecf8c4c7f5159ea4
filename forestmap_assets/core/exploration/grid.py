"""The exploration grid (men_spec 3.5): square ``cell_m`` cells over the plot, each with a height
histogram in
``dz_m`` levels, heights relative to the local ground taken from the merged lowest-hit elevation map
(men_spec 10);
the thesis's flat index ``ix*N_y*N_z + iy*N_z + iz``, the plot polygon and the grid built from every
scan's surface."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import ndimage

from forestmap_assets.core.exploration import _grid_kernels as kernels
from forestmap_assets.core.features.elevation import ElevationGrid
from forestmap_assets.params.men import ExplorationConfig


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
        iz, ok = self._levels(h, inside)
        return np.where(ok, (ix * self.ny + iy) * self.nz + iz, -1), ok

    def _levels(self, h, inside) -> tuple[np.ndarray, np.ndarray]:
        """Height level ``iz`` of each point and whether it lies inside B (all three axes)."""
        iz = np.floor((h - self.z_min) / self.dz).astype(np.int64)
        return iz, inside & (iz >= 0) & (iz < self.nz)

    def add_points(
        self,
        points: np.ndarray,
        weights: np.ndarray | None = None,
        measured: np.ndarray | None = None,
    ) -> ExplorationGrid:
        """``Eg[flat_index] += weight`` for every point (men_spec 3.5 update), in place.

        ``measured``: the share of each weight that is measured returns (default: all of it),
        kept in ``measured`` and ``points``; points above the top level go to ``above``, points
        outside B or below the bottom level are dropped. One compiled pass
        (:func:`._grid_kernels.accumulate`), summed as ``np.bincount`` sums."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        w = np.ones(len(pts)) if weights is None else np.asarray(weights, dtype=np.float64)
        m = w if measured is None else np.asarray(measured, dtype=np.float64)
        sums = [np.zeros(self.counts.size), np.zeros(self.counts.size), np.zeros(self.nx * self.ny),
                np.zeros(self.nx * self.ny)]  # counts, measured, above, points: as np.bincount
        col = lambda a: np.ascontiguousarray(np.broadcast_to(a, len(pts)), dtype=np.float64)  # noqa: E731
        kernels.accumulate(col(pts[:, 0]), col(pts[:, 1]), col(pts[:, 2]), col(w), col(m),
                           *self._kernel_grid(), *sums)
        self.counts += sums[0]
        self.measured += sums[1]
        self.above += sums[2].reshape(self.shape)
        self.points += sums[3].reshape(self.shape)
        return self

    def _kernel_grid(self) -> tuple:
        """The grid's geometry and ground as :mod:`._grid_kernels` takes them."""
        has_ground = self.ground_z is not None
        ground = np.ascontiguousarray(self.ground_z if has_ground else np.zeros((1, 1)), dtype=np.float64)
        return (float(self.x0), float(self.y0), float(self.cell_m), int(self.nx), int(self.ny),
                float(self.z_min), float(self.dz), int(self.nz), ground, has_ground)

    def add_surface(
        self, surface: pd.DataFrame, voxel_m: float, pose, max_range_m: float | None = None
    ) -> ExplorationGrid:
        """One scan's observed surface (:data:`~.surface.SURFACE_COLUMNS`, levelled scan frame,
        ``pose`` of the scan) added in place with weights ``n_points + n_filled`` (``n_points``
        measured), voxels farther than ``max_range_m`` horizontally from the scanner left out:
        :func:`~.surface.surface_points` then :meth:`add_points` in one compiled pass (the
        weights are whole numbers, so the sums do not depend on their order)."""
        if not len(surface):
            return self
        for name in ("counts", "measured", "above", "points"):  # the kernel writes into them
            setattr(self, name, np.ascontiguousarray(getattr(self, name), dtype=np.float64))
        col = lambda c: np.ascontiguousarray(surface[c].to_numpy(), dtype=np.int64)  # noqa: E731
        kernels.accumulate_surface(
            col("ix"), col("iy"), col("iz"), col("n_points"), col("n_filled"), float(voxel_m),
            np.asarray(pose, dtype=np.float64), np.inf if max_range_m is None else float(max_range_m),
            *self._kernel_grid(),
            self.counts, self.measured, self.above.reshape(-1), self.points.reshape(-1),
        )  # fmt: skip
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
        grid.add_surface(table, voxel_m, pose, config.map_range_m)
    return grid
