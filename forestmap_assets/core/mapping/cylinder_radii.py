"""A stem's radius at breast height from its cylinder segments (spec 9, 10.6; forestmap's step,
used by :func:`forestmap_assets.core.mapping.trees.merge_trees`): the truncated cones' radius
at a height with a plausible taper, the weighted statistic over cylinders, and the note that
says how a DBH not measured at breast height was obtained."""

from __future__ import annotations

import numpy as np
import pandas as pd


def radius_at(cyl: pd.DataFrame, z: np.ndarray,
              max_taper_m_per_m: float | None = None, extrapolate: bool = False) -> np.ndarray:
    """Truncated-cone radius at heights ``z``, clamped to the cylinder's ends; with
    ``max_taper_m_per_m`` the cone's slope about its mid height is limited to that taper.

    ``extrapolate=True`` continues the cone beyond its ends instead, with its slope limited to
    a stem that does not widen upwards (``-max_taper_m_per_m`` to 0 m of radius per metre)."""
    z0, z1 = cyl["z0"].to_numpy(float), cyl["z1"].to_numpy(float)
    r0 = cyl["r0_m"].to_numpy(float) if "r0_m" in cyl else cyl["radius_m"].to_numpy(float)
    r1 = cyl["r1_m"].to_numpy(float) if "r1_m" in cyl else cyl["radius_m"].to_numpy(float)
    span = np.where(np.abs(z1 - z0) > 1e-6, z1 - z0, 1.0)
    if extrapolate:
        lo = -np.inf if max_taper_m_per_m is None else -max_taper_m_per_m
        slope = np.clip((r1 - r0) / span, lo, 0.0)
        return 0.5 * (r0 + r1) + (z - 0.5 * (z0 + z1)) * slope
    t = np.clip((z - z0) / span, 0.0, 1.0)  # no extrapolation of taper beyond the ends
    if max_taper_m_per_m is None:
        return r0 + t * (r1 - r0)
    slope = np.clip((r1 - r0) / span, -max_taper_m_per_m, max_taper_m_per_m)
    return 0.5 * (r0 + r1) + (t - 0.5) * span * slope


MAX_SLOPE = 0.3  # lean (dx/dz) of a stem's axis at most


def axis_slopes(cyl: pd.DataFrame, tree_of_cyl: np.ndarray, n_trees: int,
                z_max: np.ndarray | None = None, max_slope: float = MAX_SLOPE) -> np.ndarray:
    """Lean (dx/dz, dy/dz) of each tree (1-based ``tree_of_cyl``, 0: no tree), the
    ``n_circles``-weighted mean of its cylinders' axes (only those starting below ``z_max`` of
    their tree when given), clipped to ``max_slope``; zero for a tree without such a cylinder."""
    out = np.zeros((n_trees, 2))
    if len(cyl) == 0 or n_trees == 0:
        return out
    p0 = cyl[["x0", "y0", "z0"]].to_numpy(float)
    p1 = cyl[["x1", "y1", "z1"]].to_numpy(float)
    dz = p1[:, 2] - p0[:, 2]
    ok = np.abs(dz) > 0.05
    slope = np.where(ok[:, None], (p1[:, :2] - p0[:, :2]) / np.where(ok, dz, 1.0)[:, None], 0.0)
    k = np.asarray(tree_of_cyl, dtype=int) - 1
    ok &= k >= 0
    k = np.maximum(k, 0)
    if z_max is not None:
        ok &= np.minimum(p0[:, 2], p1[:, 2]) < np.asarray(z_max, float)[k]
    w = np.where(ok, cyl["n_circles"].to_numpy(float), 0.0)
    sw = np.bincount(k, w, minlength=n_trees)
    for j in range(2):
        num = np.bincount(k, w * slope[:, j], minlength=n_trees)
        out[:, j] = np.where(sw > 0, num / np.where(sw > 0, sw, 1.0), 0.0)
    return np.clip(out, -max_slope, max_slope)


def weighted_stat(values: np.ndarray, weights: np.ndarray, statistic: str) -> float:
    """Weighted ``"mean"`` or ``"median"`` (the smallest value whose cumulative weight reaches
    half the total; the mean of the two middle values when it lands exactly on half)."""
    if statistic == "mean":
        return float(np.average(values, weights=weights))
    if statistic != "median":
        raise ValueError(f"dbh_statistic: unknown {statistic!r} (expected 'mean' or 'median')")
    order = np.argsort(values)
    v, c = values[order], np.cumsum(weights[order])
    half = 0.5 * c[-1]
    k = int(np.searchsorted(c, half))
    if k + 1 < v.size and np.isclose(c[k], half):
        return float(0.5 * (v[k] + v[k + 1]))
    return float(v[k])


def scan_median(r: np.ndarray, w: np.ndarray, scan: np.ndarray | None) -> float:
    """The median over scans of each scan's weighted mean radius ``r`` (weights ``w``): one
    vote a scan, so a near scan's heavy cylinders cannot set it alone; without ``scan``, the
    weighted median of the cylinders."""
    if scan is None:
        return weighted_stat(r, w, "median")
    _, k = np.unique(scan, return_inverse=True)
    return float(np.median(np.bincount(k, w * r) / np.bincount(k, w)))


def dbh_note_for(lo: np.ndarray, hi: np.ndarray, gap: np.ndarray, breast_height_m: float,
                 extrapolated_beyond_m: float | None, why: str = "") -> str:
    """How a DBH was obtained from the cylinders spanning heights ``lo``-``hi`` above the
    ground, ``gap`` from breast height: empty when one spans breast height; else the radius at
    their nearest ends or, with ``extrapolated_beyond_m`` (the reach none of them is within),
    their cones extrapolated to breast height; ``why`` says why they were, instead of "no
    cylinder within that reach" (where nearer ones were set aside)."""
    if (gap <= 0.0).any():
        return ""
    above = lo > breast_height_m
    n = len(gap)
    which = f"{n} cylinder{'s' if n > 1 else ''}"
    parts = []
    if above.any():
        parts.append(f"starting {_span(lo[above])} m")
    if (~above).any():
        parts.append(f"ending {_span(hi[~above])} m")
    heights = " or ".join(parts) + " above the ground"
    side = "above" if above.all() else "below" if not above.any() else "above or below"
    if extrapolated_beyond_m is None:
        return (f"no cylinder at breast height: radius at the nearest end of {which} {heights} "
                f"({_span(gap)} m {side} breast height)")
    direction = "down" if above.all() else "up" if not above.any() else "down or up"
    why = why or f"no cylinder within {extrapolated_beyond_m:g} m of breast height"
    return f"{why}: taper extrapolated {_span(gap)} m {direction} from {which} {heights}"


def _span(v: np.ndarray) -> str:
    """``"1.2"`` or ``"1.2-1.9"`` (one decimal)."""
    a, b = f"{np.min(v):.1f}", f"{np.max(v):.1f}"
    return a if a == b else f"{a}-{b}"
