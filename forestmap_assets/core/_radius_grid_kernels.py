"""Numba kernels of :class:`~forestmap_assets.core.radius_grid.RadiusGrid`: the points sorted into
vertical columns of a square grid (by column, then by height), and the nearest point within a
radius found in the columns the radius reaches (a binary search on height in each)."""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(cache=True)
def build_columns(points, lo, cell, nx, ny):
    """Column offsets (``nx * ny + 1``), the rows of ``points`` sorted by column then height
    (stable: equal heights in input order) and those points in that order."""
    n = points.shape[0]
    col = np.empty(n, np.int64)
    start = np.zeros(nx * ny + 1, np.int64)
    for i in range(n):
        ix = min(max(int((points[i, 0] - lo[0]) / cell), 0), nx - 1)
        iy = min(max(int((points[i, 1] - lo[1]) / cell), 0), ny - 1)
        col[i] = ix * ny + iy
        start[col[i] + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    pos = start[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[pos[col[i]]] = i
        pos[col[i]] += 1
    for c in range(nx * ny):
        a, b = start[c], start[c + 1]
        if b - a > 1:
            rows = order[a:b].copy()
            z = np.empty(b - a)
            for k in range(b - a):
                z[k] = points[rows[k], 2]
            order[a:b] = rows[np.argsort(z, kind="mergesort")]
    sorted_points = np.empty((n, 3))
    for k in range(n):
        for a in range(3):
            sorted_points[k, a] = points[order[k], a]
    return start, order, sorted_points


@nb.njit(cache=True, inline="always")
def nearest_one(qx, qy, qz, radius, points, order, start, lo, cell, nx, ny):
    """The squared distance to the nearest of the sorted ``points`` within ``radius`` (strictly)
    of ``(qx, qy, qz)`` and its position in them (-1 where there is none). Ties go to the lower
    input row."""
    r2 = radius * radius
    if not (math.isfinite(qx) and math.isfinite(qy) and math.isfinite(qz)):
        return r2, -1
    x0 = max(int(math.floor((qx - radius - lo[0]) / cell)), 0)
    x1 = min(int(math.floor((qx + radius - lo[0]) / cell)), nx - 1)
    y0 = max(int(math.floor((qy - radius - lo[1]) / cell)), 0)
    y1 = min(int(math.floor((qy + radius - lo[1]) / cell)), ny - 1)
    z_lo, z_hi = qz - radius, qz + radius
    best, hit = r2, -1
    for ix in range(x0, x1 + 1):
        for iy in range(y0, y1 + 1):
            c = ix * ny + iy
            b = start[c + 1]
            low, high = start[c], b
            while low < high:  # the column's first point at or above z_lo
                mid = (low + high) >> 1
                if points[mid, 2] < z_lo:
                    low = mid + 1
                else:
                    high = mid
            j = low
            while j < b and points[j, 2] <= z_hi:
                dx = points[j, 0] - qx
                dy = points[j, 1] - qy
                dz = points[j, 2] - qz
                d2 = dx * dx + dy * dy + dz * dz
                if d2 < best or (d2 == best and hit >= 0 and order[j] < order[hit]):
                    best, hit = d2, j
                j += 1
    return best, hit


@nb.njit(cache=True, parallel=True)
def nearest_within(queries, rows, radius, points, order, start, lo, cell, nx, ny, out_d, out_i):
    """For each query row in ``rows``: the distance to the nearest point within ``radius`` and
    its input row (left as they are, ``inf`` and ``n``, where there is none). Ties go to the
    lower input row."""
    for kk in nb.prange(rows.shape[0]):
        k = rows[kk]
        best, hit = nearest_one(queries[k, 0], queries[k, 1], queries[k, 2], radius, points, order, start, lo,
                                cell, nx, ny)
        if hit >= 0:
            out_d[k] = math.sqrt(best)
            out_i[k] = order[hit]
