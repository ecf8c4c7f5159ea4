"""Synthetic cylinder-segment sub-maps for testing and benchmarking registration (inferred).

Not part of the thesis method: a stand-in for feature extraction output (spec 13.6). Stems are
slightly tilted vertical segments on a gently sloping ground; each scan sees the stems within its
range that are not occluded, each over its own visible height interval, with a perturbed axis
(feature-fit error), plus a few false short cylinders of its own (clutter).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from forestmap_assets.core.geometry import rot_z


@dataclass
class StemPair:
    """Two sub-maps' cylinder tables (each in its own levelled frame) and the truth."""

    cylinders_a: pd.DataFrame
    cylinders_b: pd.DataFrame
    truth: tuple[float, float, float, float]  # pose of B in A's frame (dx, dy, dz, dh_deg)
    stems: pd.DataFrame  # world (= A frame) stem axes: x0..z1, radius_m


def random_stems(
    rng: np.random.Generator,
    n: int,
    half_extent_m: float,
    min_spacing_m: float = 1.0,
    tilt_deg: float = 4.0,
    height_m: tuple[float, float] = (4.0, 6.0),
    ground_slope: float = 0.05,
) -> pd.DataFrame:
    """``n`` stems in a square plot, at least ``min_spacing_m`` apart, bases on a sloping ground
    1.5 m below the first scanner; returns ``x0..z1`` (base, top) and ``radius_m``."""
    pts = np.empty((0, 2))
    while len(pts) < n:
        cand = rng.uniform(-half_extent_m, half_extent_m, (4 * n, 2))
        for c in cand:  # rejection sampling of a handful of stems (not a per-point loop)
            if len(pts) == 0 or np.min(np.hypot(*(pts - c).T)) >= min_spacing_m:
                pts = np.vstack([pts, c])
            if len(pts) == n:
                break
    slope = rng.normal(0, ground_slope, 2)
    z0 = -1.5 + pts @ slope
    tilt = np.radians(rng.uniform(0, tilt_deg, n))
    az = rng.uniform(0, 2 * np.pi, n)
    h = rng.uniform(*height_m, n)
    top = np.column_stack(
        [pts[:, 0] + h * np.sin(tilt) * np.cos(az), pts[:, 1] + h * np.sin(tilt) * np.sin(az), z0 + h * np.cos(tilt)]
    )
    return pd.DataFrame(
        {
            "x0": pts[:, 0], "y0": pts[:, 1], "z0": z0,
            "x1": top[:, 0], "y1": top[:, 1], "z1": top[:, 2],
            "radius_m": rng.uniform(0.08, 0.25, n),
        }
    )


def lattice_stems(spacing_m: float, n_side: int, height_m: float = 5.0) -> pd.DataFrame:
    """A perfectly regular square lattice of vertical stems (an ambiguous layout, spec 13.7)."""
    g = (np.arange(n_side) - (n_side - 1) / 2) * spacing_m
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    z0 = np.full_like(x, -1.5)
    return pd.DataFrame(
        {"x0": x, "y0": y, "z0": z0, "x1": x, "y1": y, "z1": z0 + height_m, "radius_m": 0.15}
    )


def observe(
    stems: pd.DataFrame,
    pose: tuple[float, float, float, float],
    rng: np.random.Generator,
    max_range_m: float = 12.0,
    visible_share: float = 0.7,
    axis_noise_m: float = 0.02,
    n_clutter: int = 3,
    visible_height_m: tuple[float, float] = (2.0, 3.5),
) -> pd.DataFrame:
    """Cylinder table of the stems seen from a scanner at ``pose`` (in the stems' frame), in the
    scanner's levelled frame: each visible stem over a random visible interval (start 0-0.6 m
    above its base, length in ``visible_height_m``), axis end points perturbed by
    ``axis_noise_m`` horizontally, plus ``n_clutter`` false short cylinders."""
    p0 = stems[["x0", "y0", "z0"]].to_numpy(float)
    p1 = stems[["x1", "y1", "z1"]].to_numpy(float)
    dist = np.hypot(p0[:, 0] - pose[0], p0[:, 1] - pose[1])
    seen = (dist <= max_range_m) & (rng.uniform(size=len(p0)) < visible_share)
    p0, p1 = p0[seen], p1[seen]
    axis = p1 - p0
    length = np.linalg.norm(axis, axis=1)
    start = rng.uniform(0.0, 0.6, len(p0))
    stop = np.minimum(start + rng.uniform(*visible_height_m, len(p0)), length)
    a = p0 + axis * (start / length)[:, None]
    b = p0 + axis * (stop / length)[:, None]
    noise = rng.normal(0, axis_noise_m, (2, len(p0), 3)) * np.array([1.0, 1.0, 0.0])
    a, b = a + noise[0], b + noise[1]
    if n_clutter:
        c = np.column_stack(
            [rng.uniform(-max_range_m, max_range_m, (n_clutter, 2)) * 0.7 + np.array(pose[:2]),
             rng.uniform(-1.0, 1.0, n_clutter)]
        )
        a = np.vstack([a, c])
        b = np.vstack([b, c + np.column_stack([rng.normal(0, 0.1, (n_clutter, 2)),
                                               rng.uniform(0.5, 1.5, n_clutter)])])
    rot = rot_z(-pose[3])
    la = (a - np.asarray(pose[:3])) @ rot.T
    lb = (b - np.asarray(pose[:3])) @ rot.T
    n = len(la)
    return pd.DataFrame(
        {
            "cylinder_id": np.arange(n),
            "x0": la[:, 0], "y0": la[:, 1], "z0": la[:, 2],
            "x1": lb[:, 0], "y1": lb[:, 1], "z1": lb[:, 2],
            "radius_m": 0.15, "r0_m": 0.15, "r1_m": 0.15,
            "n_circles": 10, "length_m": np.linalg.norm(lb - la, axis=1),
        }
    )


def stem_pair(
    seed: int = 0,
    n_trees: int = 45,
    half_extent_m: float = 12.0,
    offset: tuple[float, float, float, float] = (3.0, -1.5, 0.1, 35.0),
    stems: pd.DataFrame | None = None,
    **observe_kw,
) -> StemPair:
    """Two scans of one stand: A at the origin, B at ``offset`` (pose of B in A's frame)."""
    rng = np.random.default_rng(seed)
    if stems is None:
        stems = random_stems(rng, n_trees, half_extent_m)
    cyl_a = observe(stems, (0.0, 0.0, 0.0, 0.0), rng, **observe_kw)
    cyl_b = observe(stems, offset, rng, **observe_kw)
    return StemPair(cyl_a, cyl_b, tuple(float(v) for v in offset), stems)
