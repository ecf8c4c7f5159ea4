"""Ground elevation maps (spec 9; Th. 2.1.5, 6.2 Fig. 6.4, 6.3 Fig. 6.7, 6.4 Figs 6.11-6.13).

* :func:`elevation_grid`: per scan, the lowest (indoor, forest) or highest (parking lot) beam
  hit z in every ``cell_m`` xy cell of the levelled scan frame, as a sparse table
  ``ix, iy, z, n``; cell ``(ix, iy)`` covers ``[ix*cell, (ix+1)*cell) x [iy*cell, (iy+1)*cell)``
  (numba kernels in :mod:`forestmap_assets.core.features._elevation_kernels`, issue 18).
* :func:`merge_elevation`: every scan's cells transformed into the global frame with its pose
  (rotation by the heading, xy translation, z offset) and combined by the same min/max rule.
* :func:`render_grid`: the coarse 0.6 m rendering grid, each cell the mean of the 5 lowest
  values among its fine cells (Figs 6.12-6.13).
* :func:`elevation_to_table`, :func:`elevation_from_table`: the grid as a stored table.
The ``elevation.npz`` and ``elevation.png`` files are written by
:mod:`forestmap_assets.outputs.elevation_files`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import pandas as pd

from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.params import ElevationParams

Mode = Literal["lowest", "highest"]


ELEVATION_COLUMNS = ["ix", "iy", "z", "n"]


@dataclass(frozen=True)
class ElevationGrid:
    """A dense elevation grid: ``z[iy, ix]`` (NaN = no value) of the cell covering
    ``[x0 + ix*cell_m, x0 + (ix+1)*cell_m) x [y0 + iy*cell_m, y0 + (iy+1)*cell_m)``."""

    z: np.ndarray
    x0: float
    y0: float
    cell_m: float
    mode: Mode = "lowest"

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """``(xmin, xmax, ymin, ymax)`` of the grid, for ``imshow(..., origin="lower")``."""
        ny, nx = self.z.shape
        return (self.x0, self.x0 + nx * self.cell_m, self.y0, self.y0 + ny * self.cell_m)

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre coordinates ``(x[ix], y[iy])``."""
        ny, nx = self.z.shape
        return (
            self.x0 + (np.arange(nx) + 0.5) * self.cell_m,
            self.y0 + (np.arange(ny) + 0.5) * self.cell_m,
        )


# (inferred, issue 18) Largest box of cells accumulated densely (12 bytes a cell), and at most
# this many cells per used point beyond 2**20; larger boxes (far or stray points, no
# ``max_distance_m``) go through a hash table whose size follows the occupied cells.
DENSE_MAX_CELLS = 50_000_000
DENSE_CELLS_PER_POINT = 4


def _points(data: RangeImage | np.ndarray | pd.DataFrame) -> np.ndarray:
    """The points as a C-contiguous (n, 3) float64 array, a view of a range image's levelled
    ``xyz`` (NaN where no return) when possible; non-finite rows are left in (the kernels skip
    them)."""
    if isinstance(data, RangeImage):
        pts = data.xyz.reshape(-1, 3)
    elif isinstance(data, pd.DataFrame):
        pts = data[["x", "y", "z"]].to_numpy(dtype=np.float64)
    else:
        pts = np.asarray(data, dtype=np.float64).reshape(-1, 3)
    return np.ascontiguousarray(pts, dtype=np.float64)


def elevation_grid(
    data: RangeImage | np.ndarray | pd.DataFrame,
    params: ElevationParams,
    *,
    max_distance_m: float | None = None,
) -> pd.DataFrame:
    """Lowest (or highest, ``params.mode``) hit z per ``params.cell_m`` xy cell (spec 9).

    ``data`` is a range image (its levelled points), an (n, 3) array or a table with
    ``x, y, z`` in the levelled scan frame. Returns the sparse table ``ix, iy, z, n`` (``n``
    hits in the cell), sorted by ``iy, ix``. (inferred) ``max_distance_m`` limits the grid to
    ``|x|, |y| < max_distance_m`` around the sensor (the thesis' 600 x 600 cells over 60 m).
    Points with a non-finite coordinate are skipped. Among equal lowest (highest) values the
    first point's is kept, as by the stable sort of the former numpy formulation.
    """
    from forestmap_assets.core.features import _elevation_kernels as kern

    pts = _points(data)
    limit = np.inf if max_distance_m is None else float(max_distance_m)
    cell, highest = float(params.cell_m), params.mode == "highest"
    count, x0, x1, y0, y1 = kern.cell_bounds(pts, cell, limit)
    if count == 0:
        return pd.DataFrame(
            {
                "ix": pd.Series(dtype="int64"),
                "iy": pd.Series(dtype="int64"),
                "z": pd.Series(dtype="float64"),
                "n": pd.Series(dtype="int64"),
            }
        )
    nx, ny = int(x1) - int(x0) + 1, int(y1) - int(y0) + 1
    dense_max = min(DENSE_MAX_CELLS, max(1 << 20, DENSE_CELLS_PER_POINT * int(count)))
    if nx * ny <= dense_max and count < 2**31:
        ix, iy, z, n = kern.dense_cells(pts, cell, limit, highest, x0, y0, nx, ny)
    else:
        ix, iy, z, n = kern.hashed_cells(pts, cell, limit, highest)
        order = np.lexsort((ix, iy))
        ix, iy, z, n = ix[order], iy[order], z[order], n[order]
    return pd.DataFrame({"ix": ix, "iy": iy, "z": z, "n": n}, columns=ELEVATION_COLUMNS)


def merge_elevation(
    grids: Sequence[tuple[pd.DataFrame, Sequence[float]]],
    cell_m: float,
    mode: Mode = "lowest",
    *,
    supersample: int = 2,
) -> ElevationGrid:
    """Merge per-scan elevation tables into one global grid (spec 9, Th. 6.4).

    Each ``(table, pose)`` has pose = ``(x, y, z, heading_deg)`` of the scan in the global frame
    and ``table`` cells of size ``cell_m``; every cell is transformed ``p_g = R_z(heading) p + t``
    and the global cell keeps the min (``mode="lowest"``) or max of what falls into it.
    (inferred) Each source cell is represented by ``supersample`` x ``supersample`` points
    spread over it rather than by its centre only (``supersample=1``), so that a rotated grid
    leaves no aliasing holes when re-binned at the same cell size.
    """
    from forestmap_assets.core.features import _elevation_kernels as kern

    k = max(1, int(supersample))
    offs = (np.arange(k) + 0.5) / k
    ox, oy = (a.ravel() for a in np.meshgrid(offs, offs, indexing="xy"))
    used = [(table, pose) for table, pose in grids if len(table)]
    if not used:
        return ElevationGrid(np.full((0, 0), np.nan), 0.0, 0.0, float(cell_m), mode)
    cols = {c: np.concatenate([t[c].to_numpy(dtype=np.float64) for t, _ in used]) for c in ("ix", "iy", "z")}
    starts = np.cumsum([0] + [len(t) for t, _ in used])
    poses = np.array([(np.cos(np.radians(float(h))), np.sin(np.radians(float(h))), float(px), float(py), float(pz))
                      for _, (px, py, pz, h) in used])
    # one pass for the box, one for the min (max) per cell; no per-sample arrays (51 scans:
    # 8 s of sorting 20 M samples before, issue 17)
    out, gx0, gy0 = kern.merged_cells(cols["ix"], cols["iy"], cols["z"], starts, poses, ox, oy, float(cell_m),
                                      mode == "highest")
    return ElevationGrid(out, float(gx0 * cell_m), float(gy0 * cell_m), float(cell_m), mode)


def render_grid(grid: ElevationGrid, cell_m: float = 0.6, n_lowest: int = 5) -> ElevationGrid:
    """Coarse rendering grid (spec 9, Figs 6.12-6.13): each ``cell_m`` cell is the mean of the
    ``n_lowest`` smallest values among its fine cells that have values (inferred: of the largest
    ones for a ``"highest"`` grid). Fine cells are assigned by their centres; the coarse grid
    shares the fine grid's origin."""
    ny, nx = grid.z.shape
    iy, ix = np.nonzero(np.isfinite(grid.z))
    if ix.size == 0:
        return ElevationGrid(np.full((0, 0), np.nan), grid.x0, grid.y0, float(cell_m), grid.mode)
    cx = np.floor((ix + 0.5) * grid.cell_m / cell_m).astype(np.int64)
    cy = np.floor((iy + 0.5) * grid.cell_m / cell_m).astype(np.int64)
    ncx = int(np.floor(nx * grid.cell_m / cell_m - 1e-9)) + 1
    ncy = int(np.floor(ny * grid.cell_m / cell_m - 1e-9)) + 1
    keys = cy * ncx + cx
    z = grid.z[iy, ix]
    order = np.lexsort((z if grid.mode == "lowest" else -z, keys))
    k, zs = keys[order], z[order]
    start = np.searchsorted(k, k, side="left")
    rank = np.arange(k.size) - start
    sel = rank < n_lowest
    sums = np.bincount(k[sel], zs[sel], minlength=ncx * ncy)
    counts = np.bincount(k[sel], minlength=ncx * ncy)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(counts > 0, sums / counts, np.nan)
    return ElevationGrid(out.reshape(ncy, ncx), grid.x0, grid.y0, float(cell_m), grid.mode)


def elevation_to_table(grid) -> pd.DataFrame:
    """A merged elevation grid as a sparse table (ix, iy, z) plus its origin columns."""
    iy, ix = np.nonzero(np.isfinite(grid.z))
    df = pd.DataFrame(
        {
            "ix": ix.astype(np.int32),
            "iy": iy.astype(np.int32),
            "z": grid.z[iy, ix].astype(np.float32),
        }
    )
    meta = pd.DataFrame(
        {
            "x0": [grid.x0],
            "y0": [grid.y0],
            "cell_m": [grid.cell_m],
            "nx": [grid.z.shape[1]],
            "ny": [grid.z.shape[0]],
        }
    )
    return (
        df.assign(**{k: np.repeat(meta[k].to_numpy(), len(df)) for k in meta})
        if len(df)
        else df.assign(**{k: pd.Series(dtype=meta[k].dtype) for k in meta})
    )


def elevation_from_table(df: pd.DataFrame):
    """Inverse of :func:`elevation_to_table`."""
    if df.empty:
        return ElevationGrid(z=np.full((1, 1), np.nan), x0=0.0, y0=0.0, cell_m=0.1)
    nx, ny = int(df["nx"].iloc[0]), int(df["ny"].iloc[0])
    z = np.full((ny, nx), np.nan)
    z[df["iy"].to_numpy(), df["ix"].to_numpy()] = df["z"].to_numpy()
    return ElevationGrid(
        z=z,
        x0=float(df["x0"].iloc[0]),
        y0=float(df["y0"].iloc[0]),
        cell_m=float(df["cell_m"].iloc[0]),
    )
