"""Observed surface of one scan (men_spec 3.1, 3.5 input): every return plus samples on the segments
between
neighbouring returns of the organised image that no occlusion boundary separates (:mod:`.occlusion`;
the gap
fill is inferred), voxelised at ``voxel_m`` in the levelled scan frame, and its voxel centres in the
global frame."""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.core._cloud_kernels import radix_sort
from forestmap_assets.core.exploration import _surface_kernels as kernels
from forestmap_assets.core.exploration.occlusion import (
    boundaries_table,
    detect_occlusions,
    point_source,
)
from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.core.geometry import transform_points
from forestmap_assets.params.men import OcclusionConfig

SURFACE_COLUMNS = ["ix", "iy", "iz", "n_points", "n_filled"]


# ---- observed surface (per scan) ----------------------------------------------------------------
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

    ``n_points``: returns in the voxel; ``n_filled``: interior samples every <= ``fill_step_m``
    on segments between neighbouring returns (tilt and pan pairs) not flagged as occlusion
    boundaries, longer than ``fill_step_m`` and not longer than ``max_fill_m`` (inferred).
    ``tilt_pair`` / ``pan_pair`` are the flagged pair masks of
    :func:`~.occlusion.detect_occlusions`. Voxel ``(ix, iy, iz)`` covers
    ``[ix*voxel_m, (ix+1)*voxel_m)`` etc.; rows sorted by voxel.

    Two passes of :func:`~._surface_kernels.surface_walk` over the returns and samples (their
    bounds, then one key per point: voxel index and fill bit), a radix sort of the keys and a
    count pass; no point array is built."""
    xyz, trig = point_source(image)
    rng = image.range_m
    rows, cols = rng.shape
    walks = (
        (-1, np.zeros((0, 0), dtype=bool), 0),
        (0, np.asarray(tilt_pair, dtype=bool), max(rows - 1, 0)),
        (1, np.asarray(pan_pair, dtype=bool), cols if wrap else max(cols - 1, 0)),
    )

    def walk(lo, hi, span, keys):
        n = 0
        for axis, flagged, n_pairs in walks:
            n = kernels.surface_walk(
                xyz, rng, trig, flagged, axis, n_pairs, fill_step_m, max_fill_m, voxel_m,
                lo, hi, span, keys, n,
            )  # fmt: skip
        return n

    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    n = walk(lo, hi, lo, np.zeros(0, dtype=np.int64))
    if n == 0:
        return pd.DataFrame({c: pd.Series(dtype="int32") for c in SURFACE_COLUMNS})
    lo, hi = np.floor(lo / voxel_m).astype(np.int64), np.floor(hi / voxel_m).astype(np.int64)
    span = hi - lo + 1
    top = 2 * int(span[0]) * int(span[1]) * int(span[2])  # keys < top
    if top >= 2**63:
        raise ValueError(f"observed surface: {span.tolist()} voxels of {voxel_m} m is too large")
    keys = np.empty(n, dtype=np.int64)
    walk(lo, hi, span, keys)
    uniq, n_points, n_filled = kernels.voxel_counts(radix_sort(keys, top.bit_length(), False)[0])
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
    scanner are left out (the exploration grid adds a scan's surface in one compiled pass
    instead, :meth:`.grid.ExplorationGrid.add_surface`)."""
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


def scan_surface(image, config: OcclusionConfig) -> dict[str, pd.DataFrame]:
    """The ``occlusion_boundaries`` bundle of one range image: ``boundaries`` (flagged pixels),
    ``surface`` (observed-surface voxels, levelled scan frame) and ``info`` (one row)."""
    ob = detect_occlusions(image, **config.detector_kwargs())
    table = boundaries_table(image, ob)
    surface = observed_surface(
        image,
        ob.tilt_pair,
        ob.pan_pair,
        voxel_m=config.surface_voxel_m,
        fill_step_m=config.fill_step_m,
        max_fill_m=config.max_fill_m,
        wrap=ob.wrap,
    )
    rows, cols = image.shape
    info = pd.DataFrame(
        {
            "rows": [rows],
            "cols": [cols],
            "wrap": [ob.wrap],
            "voxel_m": [config.surface_voxel_m],
            "azimuth_step_deg": [image.azimuth_step_deg],
            "elevation_step_deg": [image.elevation_step_deg],
            "median_tilt_threshold": [ob.median_threshold("tilt")],
            "median_pan_threshold": [ob.median_threshold("pan")],
            "valid_pixels": [int(image.valid.sum())],
            "boundary_pixels": [int(ob.boundary.sum())],
        }
    )
    return {"boundaries": table, "surface": surface, "info": info, "_mask": ob.boundary}
