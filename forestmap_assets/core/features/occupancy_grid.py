"""3-D occupancy grid of one levelled scan (spec 5 step 1; Th. 4.7, largely inferred): cubic cell_m
cells, beams cast through the grid: cells before the hit are FREE, the hit cell OCCUPIED, all others
UNKNOWN; beams without return mark nothing."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from forestmap_assets.core.features.range_image import RangeImage

UNKNOWN, FREE, OCCUPIED = np.uint8(0), np.uint8(1), np.uint8(2)


# ---- step 1: occupancy grid -------------------------------------------------------------------
@dataclass(frozen=True)
class OccupancyGrid:
    """Dense 3-D occupancy grid (spec 5 step 1) in the levelled scan frame.

    ``state[i, j, k]`` is ``UNKNOWN``, ``FREE`` or ``OCCUPIED`` for the cell with global indices
    ``lo + (i, j, k)``, covering ``[(lo_x + i) * cell_m, (lo_x + i + 1) * cell_m)`` etc., so that
    grids of different scans share cell boundaries.
    """

    state: np.ndarray
    lo: np.ndarray
    cell_m: float

    @property
    def free_columns(self) -> np.ndarray:
        """(nx, ny) bool: xy columns with at least one free cell (spec 5 step 2)."""
        return (self.state == FREE).any(axis=2)

    @property
    def top_free_z(self) -> np.ndarray:
        """(nx, ny) z of the top of the highest free cell per column, NaN for non-free columns."""
        free = self.state == FREE
        nz = free.shape[2]
        top = nz - 1 - np.argmax(free[:, :, ::-1], axis=2)
        z = (self.lo[2] + top + 1) * self.cell_m
        return np.where(free.any(axis=2), z, np.nan)

    def cell_index(self, points: np.ndarray) -> np.ndarray:
        """Array indices (n, 3) into ``state`` of points (n, 3), without bounds checks."""
        return np.floor(np.asarray(points) / self.cell_m).astype(np.int64) - self.lo


def _beam_subsample(valid: np.ndarray, max_beams: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel (row, col) indices of the beams cast for free space (inferred).

    Rows (elevations) are thinned first and all azimuths kept, because every xy column is crossed
    by beams of many elevations but only of its own azimuth: thinning azimuth would leave holes in
    the projected free space at long range.
    """
    rows, cols = valid.shape
    n = int(valid.sum())
    if n <= max_beams:
        return np.nonzero(valid)
    row_stride = int(min(np.ceil(n / max_beams), max(1, rows // 8)))
    kept_rows = np.arange(row_stride // 2, rows, row_stride)
    n_rows = int(valid[kept_rows].sum())
    col_stride = max(1, int(np.ceil(n_rows / max_beams)))
    kept_cols = np.arange(col_stride // 2, cols, col_stride)
    sub = np.zeros_like(valid)
    sub[np.ix_(kept_rows, kept_cols)] = True
    return np.nonzero(valid & sub)


def occupancy_grid(
    image: RangeImage,
    cell_m: float,
    max_range_m: float,
    *,
    max_beams: int = 100_000,
    step_fraction: float = 0.5,
    hit_margin_m: float | None = None,
    max_cells: int = 150_000_000,
    chunk_samples: int = 2_000_000,
) -> OccupancyGrid:
    """Cast every beam through a cubic ``cell_m`` grid (spec 5 step 1, Th. 4.7.1).

    Each beam is sampled at ``step_fraction * cell_m`` steps from the sensor up to its hit
    (inferred sampled traversal instead of Amanatides-Woo); cells with a sample are free, cells
    with a hit are occupied (occupied wins), the rest unknown. Beams without return mark nothing.
    (inferred) The last ``hit_margin_m`` (default one cell) before a hit is not marked free, so
    range noise and grazing incidence do not mark wall cells that happen to hold no hit as free.
    A beam longer than ``max_range_m`` marks free space up to ``max_range_m`` and no hit
    (inferred). Hits use every pixel; free space uses at most ``max_beams`` beams (inferred).
    """
    if cell_m <= 0 or max_range_m <= 0:
        raise ValueError("cell_m and max_range_m must be positive")
    r = image.range_m.astype(np.float64)
    valid = image.valid
    xyz = image.xyz
    hit_mask = valid & (r <= max_range_m)
    hits = xyz[hit_mask]

    v, u = _beam_subsample(valid, max_beams)
    beam_r = r[v, u]
    dirs = xyz[v, u] / beam_r[:, None]
    lengths = np.minimum(beam_r, max_range_m)
    ends = dirs * lengths[:, None]
    margin = cell_m if hit_margin_m is None else float(hit_margin_m)
    free_len = np.where(beam_r <= max_range_m, np.maximum(beam_r - margin, 0.0), lengths)

    extent = np.vstack([np.zeros((1, 3)), hits, ends])
    lo = np.floor(extent.min(axis=0) / cell_m).astype(np.int64)
    hi = np.floor(extent.max(axis=0) / cell_m).astype(np.int64)
    shape = tuple(int(s) for s in (hi - lo + 1))
    if int(np.prod(shape)) > max_cells:
        raise ValueError(
            f"occupancy grid of {shape} cells exceeds max_cells={max_cells}; "
            "use a larger cell_m or a smaller max_range_m"
        )
    state = np.zeros(shape, dtype=np.uint8)
    flat = state.reshape(-1)

    step = step_fraction * cell_m
    n_samples = np.ceil(free_len / step).astype(np.int64)  # samples at t = j * step < free_len
    total = int(n_samples.sum())
    n_chunks = max(1, int(np.ceil(total / chunk_samples)))
    increment = dirs * (step / cell_m)  # one sample step, in cells
    for part in np.array_split(np.arange(lengths.size), n_chunks):
        if part.size == 0:
            continue
        ns = n_samples[part]
        beam = np.repeat(np.arange(part.size), ns)
        j = np.arange(beam.size) - np.repeat(np.cumsum(ns) - ns, ns)  # sample number on its beam
        cells = np.floor(increment[part][beam] * j[:, None] - lo).astype(np.intp)
        flat[np.ravel_multi_index(cells.T, shape, mode="clip")] = FREE

    if hits.size:
        cells = np.floor(hits / cell_m).astype(np.intp) - lo
        flat[np.ravel_multi_index(cells.T, shape, mode="clip")] = OCCUPIED
    return OccupancyGrid(state=state, lo=lo, cell_m=float(cell_m))
