"""Registration points of a sub-map (spec 6.2, Th. Fig. 5.4, Eq. 5.15-5.16; JP eq. (5)).

A sub-map's registration points are sampled every ``spacing_m`` (Delta_d = 0.05 m) along each
cylinder segment's centre line and each wall line, in the levelled scan frame. Radii are not used.
The sampling mismatch between two sub-maps is uniform within +-Delta_d/2 (eps_d = Delta_d/sqrt(12)).

Feature weighting (inferred, issue 10): Olson's score is a sum over points, so a feature counts
as much as its sampled length. A wall line fixes only its normal (and the heading); its extent
along the wall is where the scanner happened to detect it (line recall falls with range), so
two sub-maps' collinear lines overlap *more* when the scans are slid towards each other along
the wall, and on a corridor this overlap outvotes the pillars that fix the along-wall position
(benchmarks/results.md, "Structured sites"). ``cylinder_weight`` k samples cylinder centre lines
k times as densely (every Delta_d / k), i.e. weight k per metre of cylinder: k = 2 counts a
vertical cylinder's point-to-point match (two horizontal coordinates) against a line's
point-to-line match (one) by their Fisher information (2 vs 1 per point, isotropic sigma).
k = 1 is the thesis.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

SUBMAP_COLUMNS = ("x", "y", "z", "feature", "feature_id")


def empty_submap() -> pd.DataFrame:
    """A well-formed sub-map table with no points."""
    return pd.DataFrame(
        {
            "x": pd.Series([], dtype="float64"),
            "y": pd.Series([], dtype="float64"),
            "z": pd.Series([], dtype="float64"),
            "feature": pd.Series([], dtype="object"),
            "feature_id": pd.Series([], dtype="int64"),
        }
    )


def sample_segments(p0: np.ndarray, p1: np.ndarray, spacing_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``spacing_m`` along segments ``p0 -> p1`` (both ends included when the length
    is a multiple of the spacing), and the index of the segment each point came from.

    A segment of length L gives ``floor(L / spacing) + 1`` points starting at ``p0``
    (spec 6.2, Delta_d); a zero-length segment gives its single point.
    """
    p0 = np.asarray(p0, dtype=float).reshape(-1, 3)
    p1 = np.asarray(p1, dtype=float).reshape(-1, 3)
    if spacing_m <= 0:
        raise ValueError(f"spacing_m: must be positive, got {spacing_m}")
    length = np.linalg.norm(p1 - p0, axis=1)
    ok = np.isfinite(length)
    counts = np.where(ok, np.floor(length / spacing_m + 1e-9).astype(np.int64) + 1, 0)
    seg = np.repeat(np.arange(len(p0)), counts)
    start = np.repeat(np.cumsum(counts) - counts, counts)
    k = np.arange(counts.sum()) - start
    direction = np.divide(
        p1 - p0, length[:, None], out=np.zeros_like(p0), where=length[:, None] > 0
    )
    pts = p0[seg] + direction[seg] * (k * spacing_m)[:, None]
    return pts, seg


def build_submap(
    cylinders: pd.DataFrame | None,
    lines: pd.DataFrame | None,
    spacing_m: float = 0.05,
    cylinder_weight: int = 1,
) -> pd.DataFrame:
    """Registration points of one sub-map (spec 6.2): every ``spacing_m`` along each cylinder
    segment's centre line (``x0..z1``, bottom to top) and each wall line, levelled scan frame.
    Cylinders are sampled every ``spacing_m / cylinder_weight`` (module docstring, inferred;
    1 = the thesis).

    Columns ``x, y, z, feature`` ('cylinder' | 'line'), ``feature_id`` (the cylinder_id or
    line_id). Empty or missing inputs give an empty, well-formed table.
    """
    k = int(cylinder_weight)
    if k < 1 or k != cylinder_weight:
        raise ValueError(f"cylinder_weight: must be a positive integer, got {cylinder_weight}")
    parts = []
    for table, kind, id_col, step in ((cylinders, "cylinder", "cylinder_id", spacing_m / k),
                                      (lines, "line", "line_id", spacing_m)):
        if table is None or len(table) == 0:
            continue
        p0 = table[["x0", "y0", "z0"]].to_numpy(dtype=float)
        p1 = table[["x1", "y1", "z1"]].to_numpy(dtype=float)
        ids = (
            table[id_col].to_numpy(dtype=np.int64)
            if id_col in table
            else np.arange(len(table), dtype=np.int64)
        )
        pts, seg = sample_segments(p0, p1, step)
        parts.append(
            pd.DataFrame(
                {
                    "x": pts[:, 0],
                    "y": pts[:, 1],
                    "z": pts[:, 2],
                    "feature": pd.Series([kind] * len(pts), dtype="object"),
                    "feature_id": ids[seg],
                }
            )
        )
    if not parts:
        return empty_submap()
    return pd.concat(parts, ignore_index=True)


def submap_points(submap: pd.DataFrame) -> np.ndarray:
    """(n, 3) float array of a sub-map table's points."""
    return submap[["x", "y", "z"]].to_numpy(dtype=float).reshape(-1, 3)


def submap_reach(submap: pd.DataFrame) -> float:
    """Largest horizontal distance of a sub-map's points from its origin (0 when empty)."""
    if len(submap) == 0:
        return 0.0
    return float(np.hypot(submap["x"].to_numpy(float), submap["y"].to_numpy(float)).max())
