"""Refining a registration's dz from the two scans' ground elevation maps (spec 9, "Use").

Near-vertical trunks constrain the vertical offset of a pair only weakly (Th. 6.4: cloud sigma
z of 0.29 m for ST and RT), while the lowest-hit elevation grids of two levelled scans of the
same ground agree closely. The thesis names elevation maps as a future source for refining
registration; forestmap does it for z (inferred method, parameters below):

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
    max_range_m: float = 15.0,
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
