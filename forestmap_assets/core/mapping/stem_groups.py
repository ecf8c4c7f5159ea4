"""Cylinders of all scans grouped into stems (step 1 of :mod:`.trees`; inferred).

Two cylinders are linked when their axes, evaluated at the middle of their common height range
(or of the gap between them), are closer than ``merge_factor`` x the smaller radius +
``merge_tolerance_m``. Across a height gap the axes are extrapolated, so two leaning stems 1-2 m
apart can meet that test: a short cylinder high on one stem lines up with one low on the other
(own realistic 99: a 25 cm and a 24 cm stem 1.3 m apart read as one tree of 32.6 cm; rendered
22 and 34 lost two trees each this way). The stems are therefore kept apart: two cylinders
standing side by side over ``min_overlap_m`` of height, their axes further apart there than
their radii + ``apart_margin_m``, within ``base_height_m`` of the lowest cylinder around them,
belong to different stems, and no link joins two groups holding such a pair. Such pairs are
looked for within ``apart_reach_m`` (4 m) of each other: own realistic 174 had a fork limb
leaning 26 deg from a 28 cm stem chain it to a 28 cm stem 2.5 m away, beyond the 2 m once
looked at, and the two read as one 29 cm tree between them. Links are taken
shortest extrapolation first (cylinders overlapping in height, then across ever longer gaps;
ties by the axis distance over the tolerance), so a short cylinder joins the stem it sits on
before a far one its axis happens to point at. The rule stops at ``base_height_m`` because a
forked stem's leaders stand side by side above the fork (2-8 m up in the own simulator) and are
one tree.
Own realistic surveys 55-74 and PLY 83-106 (44 surveys, stems labelled by their true axes):
stems merged with another 10 -> 2, stems split over two groups 48 -> 49.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree


def ends(cyl: pd.DataFrame) -> np.ndarray:
    """The cylinders' axis end points ``x0, y0, z0, x1, y1, z1`` as an (n, 6) array."""
    return cyl[["x0", "y0", "z0", "x1", "y1", "z1"]].to_numpy(float)


def axis_xy(e: np.ndarray, z: np.ndarray) -> np.ndarray:
    """xy of each axis (rows of :func:`ends`) at heights ``z`` (extrapolated along the axis)."""
    dz = e[:, 5] - e[:, 2]
    t = np.where(np.abs(dz) > 1e-6, (z - e[:, 2]) / np.where(np.abs(dz) > 1e-6, dz, 1.0), 0.0)
    return e[:, :2] + t[:, None] * (e[:, 3:5] - e[:, :2])


def _axis_pairs(e: np.ndarray, mid: np.ndarray, zlo: np.ndarray, zhi: np.ndarray, reach_m: float):
    """Cylinder pairs (axis ends ``e``) with midpoints within ``reach_m`` (horizontally):
    indices, their common height range ``lo..hi`` (``lo > hi``: a gap) and the axes' distance
    at its middle."""
    i, j = cKDTree(mid[:, :2]).query_pairs(r=reach_m, output_type="ndarray").T
    lo, hi = np.maximum(zlo[i], zlo[j]), np.minimum(zhi[i], zhi[j])
    zc = 0.5 * (lo + hi)
    dist = np.hypot(*(axis_xy(e[i], zc) - axis_xy(e[j], zc)).T)
    return i, j, lo, hi, dist


def group_stems(cyl: pd.DataFrame, merge_factor: float = 0.75, merge_tolerance_m: float = 0.06, *,
                min_overlap_m: float = 0.5, apart_margin_m: float = 0.15, apart_reach_m: float = 4.0,
                base_height_m: float = 2.0) -> np.ndarray:
    """Stem label per cylinder: the 'same axis' links (module docstring), best first, never
    joining two groups that hold two stems side by side near their bases."""
    n = len(cyl)
    if n == 0:
        return np.zeros(0, dtype=int)
    e = ends(cyl)
    mid = 0.5 * (e[:, :3] + e[:, 3:])
    radius = cyl["radius_m"].to_numpy(float)
    zlo, zhi = np.minimum(e[:, 2], e[:, 5]), np.maximum(e[:, 2], e[:, 5])
    i, j, lo, hi, dist = _axis_pairs(e, mid, zlo, zhi, 1.0)
    tol = merge_factor * np.minimum(radius[i], radius[j]) + merge_tolerance_m
    links = np.flatnonzero(dist < tol)
    gap = np.maximum(lo - hi, 0.0)
    links = links[np.lexsort((dist[links] / tol[links], gap[links]))]  # shortest extrapolation first
    # pairs that are two stems: side by side, apart, near the ground around them
    a, b, alo, ahi, adist = _axis_pairs(e, mid, zlo, zhi, apart_reach_m)
    apart = np.flatnonzero((ahi - alo >= min_overlap_m) & (adist > radius[a] + radius[b] + apart_margin_m))
    if apart.size:
        around = cKDTree(mid[:, :2]).query_ball_point(0.5 * (mid[a[apart], :2] + mid[b[apart], :2]), r=1.5)
        own = np.minimum(zlo[a[apart]], zlo[b[apart]])  # two stems 3-4 m apart: none around
        base = np.array([min(zlo[k].min(initial=np.inf), z) for k, z in zip(around, own, strict=True)])
        apart = apart[alo[apart] <= base + base_height_m]
    rivals: dict[int, list[int]] = {}
    for p, q in zip(a[apart].tolist(), b[apart].tolist(), strict=True):
        rivals.setdefault(p, []).append(q)
        rivals.setdefault(q, []).append(p)
    parent = np.arange(n)
    members = {k: [k] for k in range(n)}

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for k in links.tolist():
        p, q = find(i[k]), find(j[k])
        if p == q:
            continue
        if len(members[p]) < len(members[q]):
            p, q = q, p
        if any(find(r) == p for m in members[q] for r in rivals.get(m, ())):
            continue  # q's group holds a stem standing beside one of p's
        parent[q] = p
        members[p].extend(members.pop(q))
    return np.unique([find(x) for x in range(n)], return_inverse=True)[1]
