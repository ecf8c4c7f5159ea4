"""Stem model of the virtual forest (spec 10.1): the stem table, its sampling and its truth.

Stem model (world frame, ``h`` = vertical height above ``z_base``, the ground under the stem)::

    axis(h)   = (x_base + lean_x h, y_base + lean_y h, z_base + h)
    r(h)      = r_base_m - taper_m_per_m h                   (mean radius, perpendicular to axis)
    r(h, psi) = r(h) + a2_m cos(2 (psi - phase2)) + a3_m cos(3 (psi - phase3))

``psi`` is the angle about the axis measured from the x axis projected perpendicular to the axis.
Breast height is ``h = 1.3`` m and the diameter at breast height is ``dbh_m = 2 r(1.3)``. DBH,
height and placement distributions are (inferred)."""

from __future__ import annotations

import numpy as np
import pandas as pd

BREAST_HEIGHT_M = 1.3


STEM_COLUMNS = [
    "tree_id",
    "x_base",
    "y_base",
    "z_base",
    "lean_x",
    "lean_y",
    "r_base_m",
    "taper_m_per_m",
    "height_m",
    "crown_base_m",
    "a2_m",
    "phase2_deg",
    "a3_m",
    "phase3_deg",
]


def sample_dbh(
    n: int,
    rng: np.random.Generator,
    *,
    median_m: float = 0.24,
    log_sigma: float = 0.35,
    bounds_m: tuple[float, float] = (0.07, 0.60),
) -> np.ndarray:
    """DBH from a lognormal truncated to ``bounds_m`` (inferred; mostly 0.15-0.35 m)."""
    out = np.empty(0)
    while out.size < n:
        d = median_m * np.exp(log_sigma * rng.standard_normal(2 * n + 16))
        out = np.concatenate([out, d[(d >= bounds_m[0]) & (d <= bounds_m[1])]])
    return out[:n]


def stem_height(dbh_m: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Tree height from DBH, ``1.3 + 30 (1 - exp(-0.045 d_cm))`` times U(0.9, 1.1) (inferred)."""
    return (1.3 + 30.0 * (1 - np.exp(-0.045 * dbh_m * 100))) * rng.uniform(0.9, 1.1, dbh_m.size)


def place_stems(
    radius: np.ndarray,
    scan_xy: np.ndarray,
    plot_size: float,
    rng: np.random.Generator,
    *,
    scan_clearance_m: float = 2.5,
    min_gap_m: float = 0.8,
    edge_m: float = 0.5,
    max_tries: int = 400,
) -> np.ndarray:
    """Stem positions (n, 2) inside the plot by rejection sampling: stems do not overlap each
    other (gap ``min_gap_m``) and stay ``scan_clearance_m`` from every scan position."""
    half = plot_size / 2 - edge_m
    placed = np.empty((0, 2))
    placed_r = np.empty(0)
    for r in radius:  # one iteration per tree, candidates tested vectorised
        cand = rng.uniform(-half, half, (max_tries, 2))
        ok = (np.linalg.norm(cand[:, None] - scan_xy[None], axis=2) >= scan_clearance_m + r).all(1)
        ok &= (
            np.linalg.norm(cand[:, None] - placed[None], axis=2) >= r + placed_r[None] + min_gap_m
        ).all(1)
        if not ok.any():
            raise ValueError(
                f"cannot place {radius.size} non-overlapping trees in a {plot_size} m plot "
                f"around {len(scan_xy)} scan positions; use fewer trees or a larger plot"
            )
        placed = np.vstack([placed, cand[np.argmax(ok)]])
        placed_r = np.append(placed_r, r)
    return placed


def breast_height_table(stems: pd.DataFrame) -> pd.DataFrame:
    """``tree_id, x, y, z, dbh_m`` of a stem table (any frame): axis at 1.3 m, ground z."""
    h = BREAST_HEIGHT_M
    return pd.DataFrame(
        {
            "tree_id": stems["tree_id"].to_numpy(),
            "x": stems["x_base"].to_numpy() + stems["lean_x"].to_numpy() * h,
            "y": stems["y_base"].to_numpy() + stems["lean_y"].to_numpy() * h,
            "z": stems["z_base"].to_numpy(),
            "dbh_m": 2 * (stems["r_base_m"].to_numpy() - stems["taper_m_per_m"].to_numpy() * h),
        }
    )


def stems_in_frame(stems: pd.DataFrame, origin: np.ndarray, heading_deg: float) -> pd.DataFrame:
    """Stem table expressed in a levelled frame at ``origin`` with ``heading_deg`` (world)."""
    c, s = np.cos(np.radians(heading_deg)), np.sin(np.radians(heading_deg))
    out = stems.copy()
    dx = stems["x_base"].to_numpy() - origin[0]
    dy = stems["y_base"].to_numpy() - origin[1]
    out["x_base"], out["y_base"] = c * dx + s * dy, -s * dx + c * dy
    out["z_base"] = stems["z_base"].to_numpy() - origin[2]
    lx, ly = stems["lean_x"].to_numpy(), stems["lean_y"].to_numpy()
    out["lean_x"], out["lean_y"] = c * lx + s * ly, -s * lx + c * ly
    for col in ("phase2_deg", "phase3_deg"):  # psi is measured from the (rotated) x axis
        out[col] = np.mod(stems[col].to_numpy() - heading_deg + 180.0, 360.0) - 180.0
    return out
