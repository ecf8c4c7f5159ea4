"""Refining a registration's dz from the two scans' ground elevation maps (spec 9, "Use").

Near-vertical trunks constrain the vertical offset of a pair only weakly (Th. 6.4: cloud sigma
z of 0.29 m for ST and RT), while the lowest-hit elevation grids of two levelled scans of the
same ground agree closely. The thesis names elevation maps as a future source for refining
registration; forestmap does it for z (inferred method, parameters below):

0. each grid keeps its ground-like cells (:func:`ground_cells`): a lowest hit within
   ``tol_m`` of the lowest in the ``block_m`` square about it. Far from a scanner most cells'
   lowest hit is a trunk, a branch or undergrowth (at the true pose 1-5 % of the cells 10-15 m
   from both scanners of a Sylva pair agreed within 8 cm), and the median below then settled on
   a chance mode 12-40 cm off (issue 19, benchmarks/results.md "ground_cells");
1. the scan's lowest-hit cells (cell centres, levelled scan frame) are moved into the
   reference frame with the registered (dx, dy, dz, dheading);
2. each is compared with the reference's lowest hit in the cell it falls in, for cells within
   ``max_range_m`` of both scanners (grazing hits far away are unreliable);
3. the correction is the median difference, refined twice over differences within
   ``inlier_m`` of the median (understorey and occlusion edges are outliers);
4. its sigma is 1.2533 * MAD / sqrt(n_eff) (standard error of a median), with n_eff the inlier
   count divided by ``correlation_cells`` (neighbouring cells' errors are correlated),
   floored at ``min_sd_m``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from forestmap_assets.core.geometry import transform_points

MAX_RANGE_M = 15.0  # cells compared: within this distance of both scanners


def ground_cells(grid: pd.DataFrame | None, cell_m: float, block_m: float = 0.7,
                 tol_m: float = 0.15, max_range_m: float = MAX_RANGE_M) -> pd.DataFrame | None:
    """The cells of a lowest-hit grid (``ix, iy, z``, the scanner at the origin) within
    ``max_range_m`` (+ ``block_m``) of the scanner whose z lies within ``tol_m`` of the lowest z
    in the square of ``block_m`` (odd number of cells) centred on it; ``block_m`` 0 keeps every
    cell. Ground sloping by more than ``tol_m / (block_m / 2)`` (43 % with the defaults) loses
    its cells, and the features' dz stays."""
    if grid is None or grid.empty or block_m <= 0:
        return grid
    from scipy.ndimage import minimum_filter

    reach = (max_range_m + block_m) / cell_m  # a dense array of the near cells only
    grid = grid[np.hypot(grid["ix"].to_numpy() + 0.5, grid["iy"].to_numpy() + 0.5) <= reach]
    if grid.empty:
        return grid
    ix, iy = grid["ix"].to_numpy(np.int64), grid["iy"].to_numpy(np.int64)
    z = grid["z"].to_numpy(float)
    x0, y0 = ix.min(), iy.min()
    dense = np.full((ix.max() - x0 + 1, iy.max() - y0 + 1), np.inf)
    dense[ix - x0, iy - y0] = z
    size = int(round(block_m / cell_m)) | 1
    low = minimum_filter(dense, size=size, mode="constant", cval=np.inf)[ix - x0, iy - y0]
    return grid[z - low <= tol_m]


@dataclass(frozen=True)
class GroundZ:
    dz: float
    sd: float
    n_cells: int

    @property
    def ok(self) -> bool:
        return np.isfinite(self.dz)


def ground_dz(
    scan_grid: pd.DataFrame,
    reference_grid: pd.DataFrame,
    pose,
    cell_m: float,
    *,
    max_range_m: float = MAX_RANGE_M,
    inlier_m: float = 0.08,
    min_cells: int = 50,
    correlation_cells: float = 25.0,
    min_sd_m: float = 0.005,
) -> GroundZ:
    """Vertical offset of ``scan`` in the frame of ``reference`` from their ground grids.

    ``scan_grid`` / ``reference_grid``: lowest-hit tables (``ix, iy, z``) of
    :func:`~forestmap_assets.core.features.elevation.elevation_grid`; ``pose`` the registered
    (dx, dy, dz, dheading_deg) of scan in the reference's levelled frame.
    """
    fail = GroundZ(np.nan, np.nan, 0)
    if scan_grid is None or reference_grid is None or scan_grid.empty or reference_grid.empty:
        return fail
    local = np.column_stack([
        (scan_grid["ix"].to_numpy() + 0.5) * cell_m,
        (scan_grid["iy"].to_numpy() + 0.5) * cell_m,
        scan_grid["z"].to_numpy(float),
    ])
    near_scan = np.hypot(local[:, 0], local[:, 1]) <= max_range_m
    moved = transform_points(local[near_scan], pose)
    ix = np.floor(moved[:, 0] / cell_m).astype(np.int64)
    iy = np.floor(moved[:, 1] / cell_m).astype(np.int64)
    near_ref = np.hypot((ix + 0.5) * cell_m, (iy + 0.5) * cell_m) <= max_range_m
    ix, iy, z_scan = ix[near_ref], iy[near_ref], moved[near_ref, 2]
    ref = pd.Series(reference_grid["z"].to_numpy(float),
                    index=pd.MultiIndex.from_arrays([reference_grid["ix"].to_numpy(np.int64), reference_grid["iy"].to_numpy(np.int64)]))
    z_ref = ref.reindex(pd.MultiIndex.from_arrays([ix, iy])).to_numpy()
    d = z_ref - z_scan
    d = d[np.isfinite(d)]
    if d.size < min_cells:
        return fail
    med = float(np.median(d))
    for _ in range(2):
        inl = d[np.abs(d - med) <= inlier_m]
        if inl.size < min_cells:
            return fail
        med = float(np.median(inl))
    mad = float(np.median(np.abs(inl - med)))
    n_eff = max(1.0, inl.size / correlation_cells)
    sd = max(min_sd_m, 1.2533 * 1.4826 * mad / np.sqrt(n_eff))
    return GroundZ(float(pose[2]) + med, sd, int(inl.size))
