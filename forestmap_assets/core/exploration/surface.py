"""Observed surface of one scan (men_spec 3.1, 3.5 input): every return plus samples on the segments
between
neighbouring returns of the organised image that no occlusion boundary separates (:mod:`.occlusion`;
the gap
fill is inferred), voxelised at ``voxel_m`` in the levelled scan frame, and its voxel centres in the
global frame."""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.core.exploration.occlusion import boundaries_table, detect_occlusions
from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.core.geometry import transform_points
from forestmap_assets.params.men import OcclusionConfig

SURFACE_COLUMNS = ["ix", "iy", "iz", "n_points", "n_filled"]


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
            "median_tilt_threshold": [
                float(np.median(ob.tilt_threshold)) if ob.tilt_threshold.size else np.nan
            ],
            "median_pan_threshold": [
                float(np.median(ob.pan_threshold)) if ob.pan_threshold.size else np.nan
            ],
            "valid_pixels": [int(image.valid.sum())],
            "boundary_pixels": [int(ob.boundary.sum())],
        }
    )
    return {"boundaries": table, "surface": surface, "info": info, "_mask": ob.boundary}
