"""Stem model of the virtual forest (spec 10.1): the stem table, its sampling and its truth.

Stem model (world frame, ``h`` = vertical height above ``z_base``, the ground under the stem)::

    axis(h)   = (x_base + lean_x h, y_base + lean_y h, z_base + h)
    r(h)      = r_base_m - taper_m_per_m h                   (mean radius, perpendicular to axis)
    r(h, psi) = r(h) + a2_m cos(2 (psi - phase2)) + a3_m cos(3 (psi - phase3))

``psi`` is the angle about the axis measured from the x axis projected perpendicular to the axis.
Breast height is ``h = 1.3`` m and the diameter at breast height is ``dbh_m = 2 r(1.3)``. DBH,
height and placement distributions are (inferred). These are the ``circular`` stems; the
``realistic`` stems of :mod:`.stem_shapes` (issue 19) add columns to the same table (sweep,
out-of-round sections, buttress flare and flutes, bark, forks) and keep ``r(h)`` as the mean
radius, so ``dbh_m = 2 r(1.3)`` holds for both."""

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


def sweep_offset(stems: pd.DataFrame, h) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal offset (dx, dy) of the stem axis from the straight lean line at heights ``h``
    (one per row, or broadcastable): ``sweep_m sin(pi h / height_m)`` towards ``sweep_deg``
    (realistic stems, :mod:`.stem_shapes`); zero when the table has no ``sweep_m``."""
    h = np.asarray(h, dtype=np.float64)
    if "sweep_m" not in stems.columns:
        return np.zeros_like(h), np.zeros_like(h)
    bow = stems["sweep_m"].to_numpy(float) * np.sin(np.pi * h / stems["height_m"].to_numpy(float))
    a = np.radians(stems["sweep_deg"].to_numpy(float))
    return bow * np.cos(a), bow * np.sin(a)


def breast_height_table(stems: pd.DataFrame) -> pd.DataFrame:
    """``tree_id, x, y, z, dbh_m`` of a stem table (any frame): the centre of the cross-section
    at 1.3 m above the ground under the stem (lean and sweep included), ground z, and the DBH
    ``2 (r_base_m - 1.3 taper_m_per_m)``: twice the mean radius of the cross-section at 1.3 m,
    i.e. the mean of its diameters through the centre over all directions (for an out-of-round
    stem also the mean of its largest and smallest diameter, cross-calipering; bark roughness,
    zero mean, is left out; :mod:`.stem_shapes`)."""
    h = BREAST_HEIGHT_M
    x = stems["x_base"].to_numpy() + stems["lean_x"].to_numpy() * h
    y = stems["y_base"].to_numpy() + stems["lean_y"].to_numpy() * h
    if "sweep_m" in stems.columns:
        dx, dy = sweep_offset(stems, np.full(len(stems), h))
        x, y = x + dx, y + dy
    return pd.DataFrame(
        {
            "tree_id": stems["tree_id"].to_numpy(),
            "x": x,
            "y": y,
            "z": stems["z_base"].to_numpy(),
            "dbh_m": 2 * (stems["r_base_m"].to_numpy() - stems["taper_m_per_m"].to_numpy() * h),
        }
    )


# columns that move with the frame: points (x, y, z), horizontal vectors (x, y), angles (deg)
FRAME_POINTS = (("x_base", "y_base", "z_base"), ("fork_x", "fork_y", "fork_z"))
FRAME_VECTORS = (("lean_x", "lean_y"),)
FRAME_ANGLES = ("phase2_deg", "phase3_deg", "ellipse_deg", "lobe_phase_deg", "sweep_deg",
                "fork_az_deg")


def stems_in_frame(stems: pd.DataFrame, origin: np.ndarray, heading_deg: float) -> pd.DataFrame:
    """Stem table expressed in a levelled frame at ``origin`` with ``heading_deg`` (world):
    every point, horizontal vector and angle column present (``FRAME_*``) is moved."""
    c, s = np.cos(np.radians(heading_deg)), np.sin(np.radians(heading_deg))
    out = stems.copy()
    for cx, cy, cz in FRAME_POINTS:
        if cx not in stems.columns:
            continue
        dx = stems[cx].to_numpy() - origin[0]
        dy = stems[cy].to_numpy() - origin[1]
        out[cx], out[cy] = c * dx + s * dy, -s * dx + c * dy
        out[cz] = stems[cz].to_numpy() - origin[2]
    for cx, cy in FRAME_VECTORS:
        lx, ly = stems[cx].to_numpy(), stems[cy].to_numpy()
        out[cx], out[cy] = c * lx + s * ly, -s * lx + c * ly
    for col in FRAME_ANGLES:  # psi is measured from the (rotated) x axis
        if col in stems.columns:
            out[col] = np.mod(stems[col].to_numpy() - heading_deg + 180.0, 360.0) - 180.0
    return out
