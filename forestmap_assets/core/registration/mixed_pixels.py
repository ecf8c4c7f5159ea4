"""A wide first-return beam's mixed pixels, found in a scan's range image and left out of its
refinement cloud (issue 16, inferred; benchmarks/results.md "wide_symmetric").

A first-return beam whose footprint (diameter ``exit + divergence r`` at range ``r``) touches a
nearer object returns the nearer range along its centre ray: every silhouette is widened outward
by up to one footprint radius, for each scan on the side it sees. Those pixels cannot be told
from the true edge by their own range, but they lie within one footprint radius of a range jump,
on its near side: :func:`silhouette_band` finds them there (along the pixel's row and column, in
pixels of the image's angular steps at the pixel's range)."""

from __future__ import annotations

import json

import numpy as np


def footprint_pixels(range_m: np.ndarray, exit_m: float, divergence_rad: float, step_rad: float,
                     max_pixels: int, shrink: np.ndarray | float = 1.0) -> np.ndarray:
    """The footprint radius ``(exit + divergence r) / 2`` at each range in pixels of
    ``step_rad`` (each ``r step shrink`` wide; rounded up, at most ``max_pixels``; 0 where the
    range is not finite)."""
    r = np.asarray(range_m, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.ceil((0.5 * exit_m + 0.5 * divergence_rad * r) / (r * step_rad * shrink))
    return np.where(np.isfinite(k) & (r > 0), np.minimum(k, max_pixels), 0).astype(np.int32)


def _farther_within(range_m: np.ndarray, k: np.ndarray, jump_m: float, axis: int) -> np.ndarray:
    """Pixels with a pixel at most ``k`` (their own) steps away along ``axis`` whose range is
    farther than theirs by more than ``jump_m`` (pixels without a return never count)."""
    r = np.where(np.isfinite(range_m), range_m, -np.inf)
    near = r + jump_m
    out = np.zeros(r.shape, dtype=bool)
    n = r.shape[axis]
    lo, hi = [slice(None)] * 2, [slice(None)] * 2
    for d in range(1, min(int(k.max(initial=0)), n - 1) + 1):
        reach = k >= d
        lo[axis], hi[axis] = slice(0, n - d), slice(d, n)
        a, b = tuple(lo), tuple(hi)
        out[a] |= reach[a] & (r[b] > near[a])  # the farther pixel d steps after
        out[b] |= reach[b] & (r[a] > near[b])  # ... and d steps before
    return out


def silhouette_band(range_m: np.ndarray, azimuth_step_rad: float, elevation_step_rad: float,
                    elevation_rad: np.ndarray, exit_m: float, divergence_rad: float, jump_m: float,
                    max_pixels: int = 16) -> np.ndarray:
    """Pixels (rows, cols) of an organised range image within one footprint radius (at their own
    range) of a pixel farther by more than ``jump_m``, along their row (azimuth steps, shortened
    by the cosine of the row's elevation) or their column: the near side of every range jump,
    where a wide first-return beam's mixed pixels lie. Along a column that includes the ground
    beyond a few metres, seen at a grazing angle, whose rows step away by more than ``jump_m``
    within a footprint (where a wide footprint's first return is short as well)."""
    r = np.asarray(range_m, dtype=np.float32)
    cos_el = np.maximum(np.cos(np.asarray(elevation_rad, dtype=np.float64)), 0.05)[:, None]
    k_col = footprint_pixels(r, exit_m, divergence_rad, azimuth_step_rad, max_pixels, cos_el)
    k_row = footprint_pixels(r, exit_m, divergence_rad, elevation_step_rad, max_pixels)
    return _farther_within(r, k_col, jump_m, axis=1) | _farther_within(r, k_row, jump_m, axis=0)


def table_silhouette_band(table, exit_m: float, divergence_rad: float, jump_m: float,
                          max_pixels: int = 16) -> np.ndarray:
    """:func:`silhouette_band` of a stored range image (Arrow table of valid pixels ``row, col,
    range_m``, its angles in the schema metadata), one flag per row of the table; all False
    when the beam has no footprint. Only the range channel is scattered into the image: the whole
    :meth:`~forestmap_assets.core.features.range_image.RangeImage.from_table` (its points too)
    took 0.3 s of a 1.4 M-point scan against 0.05 s."""
    n = table.num_rows
    if not (exit_m > 0 or divergence_rad > 0) or n == 0:
        return np.zeros(n, dtype=bool)
    meta = table.schema.metadata or {}
    az = np.radians(np.asarray(json.loads(meta[b"azimuth_deg"]), dtype=np.float64))
    el = np.radians(np.asarray(json.loads(meta[b"elevation_deg"]), dtype=np.float64))
    if az.size < 2 or el.size < 2:
        return np.zeros(n, dtype=bool)
    flat = table.column("row").to_numpy().astype(np.int64) * az.size + table.column("col").to_numpy()
    image = np.full(el.size * az.size, np.nan, dtype=np.float32)
    image[flat] = table.column("range_m").to_numpy()
    band = silhouette_band(image.reshape(el.size, az.size), float(np.median(np.abs(np.diff(az)))),
                           float(np.median(np.abs(np.diff(el)))), el, exit_m, divergence_rad, jump_m,
                           max_pixels)
    return band.reshape(-1)[flat]
