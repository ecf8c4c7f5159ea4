"""Horizontal wall/ceiling border lines (spec 5 steps 4-6; Th. 4.7, Figs 4.22-4.25, Table 4.3):
chains split where the tangent over tangent_interval_m turns by more than tangent_change_deg, 3-D
SVD line fit with end points within end_distance_m, acceptance by min_length_m and
max_inclination_deg; extract_line_segments runs steps 1-6."""

from __future__ import annotations

from typing import Literal

import numpy as np
import pandas as pd

from forestmap_assets.core.features.free_space_border import border_cells, border_chains
from forestmap_assets.core.features.occupancy_grid import occupancy_grid
from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.params import LineParams

LINE_COLUMNS = ["line_id", "x0", "y0", "z0", "x1", "y1", "z1", "n_points", "length_m"]


def empty_line_table() -> pd.DataFrame:
    """The well-formed empty line-segment table (columns of the shared schema)."""
    return pd.DataFrame(
        {
            c: pd.Series(dtype="int64" if c in ("line_id", "n_points") else "float64")
            for c in LINE_COLUMNS
        }
    )


# ---- step 4: splitting at tangent direction changes -------------------------------------------
def turning_angles(points_xy: np.ndarray, interval_m: float, closed: bool = False) -> np.ndarray:
    """Tangent direction change (deg) at each chain point (spec 5 step 4, inferred form).

    The tangent before point i is the chord from the point ``interval_m`` of arc length behind
    to i, the tangent after it the chord from i to the point ``interval_m`` ahead; the change is
    the angle between them. Near the ends of an open chain, where less than half an interval is
    available on a side, the change is 0. A closed chain wraps around.
    """
    p = np.asarray(points_xy, dtype=np.float64)[:, :2]
    n = p.shape[0]
    if n < 3:
        return np.zeros(n)
    seg = np.hypot(*np.diff(p, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    idx = np.arange(n)
    if closed:
        perimeter = s[-1] + float(np.hypot(*(p[0] - p[-1])))
        s = np.concatenate([s - perimeter, s, s + perimeter])
        p = np.concatenate([p, p, p])
        idx = idx + n
    back = np.clip(np.searchsorted(s, s[idx] - interval_m, side="right") - 1, 0, len(s) - 1)
    ahead = np.clip(np.searchsorted(s, s[idx] + interval_m, side="left"), 0, len(s) - 1)
    u = p[idx] - p[back]
    w = p[ahead] - p[idx]
    ok = (s[idx] - s[back] >= 0.5 * interval_m) & (s[ahead] - s[idx] >= 0.5 * interval_m)
    cos = np.einsum("ij,ij->i", u, w) / np.maximum(np.hypot(*u.T) * np.hypot(*w.T), 1e-12)
    return np.where(ok, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), 0.0)


def tangent_splits(angles_deg: np.ndarray, threshold_deg: float) -> np.ndarray:
    """Indices where a new segment starts: the largest turning point of every run of points
    whose tangent change exceeds ``threshold_deg`` (spec 5 step 4)."""
    above = np.asarray(angles_deg) > threshold_deg
    if not above.any():
        return np.zeros(0, dtype=np.int64)
    edges = np.diff(np.concatenate([[0], above.astype(np.int8), [0]]))
    run = np.cumsum(edges[:-1] == 1)
    members = np.nonzero(above)[0]
    order = np.lexsort((-np.asarray(angles_deg)[members], run[members]))
    _, first = np.unique(run[members][order], return_index=True)
    return np.sort(members[order][first])


# ---- step 5: 3-D line fit ---------------------------------------------------------------------
def fit_line(
    points: np.ndarray, end_distance_m: float
) -> tuple[np.ndarray, np.ndarray, int, float]:
    """SVD line through 3-D points (spec 5 step 5).

    Direction: largest-variance right singular vector; pass point: the centroid; end points: the
    furthest projections of the points within ``end_distance_m`` of the line. Returns
    ``(p0, p1, n_inliers, max_distance)``.
    """
    pts = np.asarray(points, dtype=np.float64)
    c = pts.mean(axis=0)
    q = pts - c
    direction = np.linalg.svd(q, full_matrices=False)[2][0]
    t = q @ direction
    dist = np.linalg.norm(q - t[:, None] * direction, axis=1)
    inl = dist <= end_distance_m
    if not inl.any():
        return c, c, 0, float(dist.max())
    p0, p1 = c + t[inl].min() * direction, c + t[inl].max() * direction
    return p0, p1, int(inl.sum()), float(dist.max())


def _chord_farthest(points: np.ndarray) -> int:
    """Interior index furthest from the chord joining the first and last point (3-D)."""
    a, b = points[0], points[-1]
    ab = b - a
    q = points - a
    nab = np.linalg.norm(ab)
    if nab < 1e-9:
        dist = np.linalg.norm(q, axis=1)
    else:
        dist = np.linalg.norm(np.cross(q, ab / nab), axis=1)
    dist[[0, -1]] = -1.0
    return int(np.argmax(dist))


def _segment_lines(
    pts: np.ndarray, params: LineParams, split_at_outliers: bool
) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """Fit lines to one tangent-split segment; (inferred) if some point lies further than
    ``end_distance_m`` from the fit, split at the point furthest from the chord and recurse
    (split-and-merge), so a corner the tangent test missed still separates two walls."""
    out = []
    stack = [(0, pts.shape[0])]
    while stack:
        a, b = stack.pop()
        seg = pts[a:b]
        if seg.shape[0] < 3:
            continue
        if (
            np.linalg.norm(seg[-1] - seg[0]) < params.min_length_m
            and np.ptp(seg, axis=0).max() < params.min_length_m
        ):
            continue
        p0, p1, n_in, dmax = fit_line(seg, params.end_distance_m)
        if split_at_outliers and dmax > params.end_distance_m and seg.shape[0] > 4:
            k = a + _chord_farthest(seg)
            stack.extend([(a, k + 1), (k, b)])
            continue
        out.append((p0, p1, n_in))
    return out


def extract_line_segments(
    image: RangeImage,
    params: LineParams,
    *,
    max_beams: int = 100_000,
    step_fraction: float = 0.5,
    hit_margin_m: float | None = None,
    min_wall_extent_m: float = 0.5,
    top_tolerance_m: float | None = None,
    wall_depth_cells: int = 2,
    border_xy: Literal["hits", "edge", "centre"] = "hits",
    link_cells: int = 2,
    split_at_outliers: bool = True,
) -> pd.DataFrame:
    """Horizontal wall/ceiling border lines of one scan (spec 5, Th. 4.7, Table 4.3).

    Returns the shared line-segment table ``line_id, x0, y0, z0, x1, y1, z1, n_points,
    length_m`` in the levelled scan frame; empty (well-formed) when ``params.enabled`` is False
    or the image has no returns. Keyword arguments are the inferred choices documented in
    :func:`occupancy_grid`, :func:`border_cells` and :func:`_segment_lines`.
    """
    if not params.enabled or not image.valid.any():
        return empty_line_table()
    grid = occupancy_grid(
        image,
        params.cell_m,
        params.max_range_m,
        max_beams=max_beams,
        step_fraction=step_fraction,
        hit_margin_m=hit_margin_m,
    )
    hits = image.xyz[image.valid & (image.range_m <= params.max_range_m)]
    border = border_cells(
        grid,
        hits,
        min_wall_extent_m=min_wall_extent_m,
        top_tolerance_m=top_tolerance_m,
        wall_depth_cells=wall_depth_cells,
        border_xy=border_xy,
    )
    if len(border) < 3:
        return empty_line_table()
    pts_all = border[["x", "y", "z"]].to_numpy()
    ix, iy = border["ix"].to_numpy(), border["iy"].to_numpy()

    found: list[tuple[np.ndarray, np.ndarray, int]] = []
    for chain in border_chains(ix, iy, min_cells=3, link_cells=link_cells):
        gap = max(abs(ix[chain[0]] - ix[chain[-1]]), abs(iy[chain[0]] - iy[chain[-1]]))
        closed = chain.size > 4 and gap <= link_cells
        pts = pts_all[chain]
        angles = turning_angles(pts, params.tangent_interval_m, closed=closed)
        splits = tangent_splits(angles, params.tangent_change_deg)
        if closed and splits.size:
            pts = np.roll(pts, -splits[0], axis=0)
            splits = splits - splits[0]
        bounds = np.unique(np.concatenate([[0], splits, [pts.shape[0]]]))
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            found.extend(_segment_lines(pts[a:b], params, split_at_outliers))

    if not found:
        return empty_line_table()
    p0 = np.array([f[0] for f in found])
    p1 = np.array([f[1] for f in found])
    n_pts = np.array([f[2] for f in found], dtype=np.int64)
    d = p1 - p0
    length = np.linalg.norm(d, axis=1)
    incl = np.degrees(np.arctan2(np.abs(d[:, 2]), np.hypot(d[:, 0], d[:, 1])))
    keep = (length >= params.min_length_m) & (incl <= params.max_inclination_deg) & (n_pts >= 2)
    if not keep.any():
        return empty_line_table()
    order = np.argsort(-length[keep], kind="stable")
    p0, p1 = p0[keep][order], p1[keep][order]
    n_pts, length = n_pts[keep][order], length[keep][order]
    return pd.DataFrame(
        {
            "line_id": np.arange(p0.shape[0], dtype=np.int64),
            "x0": p0[:, 0],
            "y0": p0[:, 1],
            "z0": p0[:, 2],
            "x1": p1[:, 0],
            "y1": p1[:, 1],
            "z1": p1[:, 2],
            "n_points": n_pts,
            "length_m": length,
        },
        columns=LINE_COLUMNS,
    )
