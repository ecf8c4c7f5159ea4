"""Numba kernels of :func:`~forestmap_assets.core.features.elevation.elevation_grid` (spec 9).

The points are read in place (an ``(n, 3)`` float64 view, e.g. of a range image's levelled
``xyz``); a point is used when its coordinates are finite and ``|x|, |y| < max_distance`` (pass
``inf`` for no limit). Its cell is ``floor(x / cell_m), floor(y / cell_m)``, the arithmetic of the
numpy formulation these kernels replaced, and each cell keeps the lowest (``highest=False``) or
highest ``z`` of its points -- the first one in input order among equal values, as the stable
sort did -- and their count. :func:`cell_bounds` gives the box of the occupied cells; then
:func:`dense_cells` accumulates in a dense grid over that box, or :func:`hashed_cells` in an
open-addressing hash table when the box is too large for one. Both return the occupied cells
``ix, iy, z, n``; the dense kernel in ``iy, ix`` order, the hashed one in first-hit order.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(cache=True, inline="always")
def _cell(p, i, cell_m, max_distance):
    """``(used, ix, iy, z)`` of point ``i``: whether it counts (finite, ``|x|, |y| <
    max_distance``) and its cell ``floor(x / cell_m), floor(y / cell_m)``."""
    x, y, z = p[i, 0], p[i, 1], p[i, 2]
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        return False, 0, 0, z
    if not (abs(x) < max_distance and abs(y) < max_distance):
        return False, 0, 0, z
    return True, int(math.floor(x / cell_m)), int(math.floor(y / cell_m)), z


@nb.njit(cache=True)
def cell_bounds(p, cell_m, max_distance):
    """``(count, ix_min, ix_max, iy_min, iy_max)`` over the used points (count 0: none)."""
    count = 0
    x0 = y0 = np.iinfo(np.int64).max
    x1 = y1 = np.iinfo(np.int64).min
    for i in range(p.shape[0]):
        used, ix, iy, _ = _cell(p, i, cell_m, max_distance)
        if not used:
            continue
        count += 1
        x0 = min(x0, ix)
        x1 = max(x1, ix)
        y0 = min(y0, iy)
        y1 = max(y1, iy)
    return count, x0, x1, y0, y1


@nb.njit(cache=True)
def dense_cells(p, cell_m, max_distance, highest, x0, y0, nx, ny):
    """Occupied cells of the box ``[x0, x0 + nx) x [y0, y0 + ny)`` in ``iy, ix`` order."""
    zc = np.empty(nx * ny, np.float64)
    nc = np.zeros(nx * ny, np.int32)
    for i in range(p.shape[0]):
        used, cx, cy, z = _cell(p, i, cell_m, max_distance)
        if not used:
            continue
        k = (cy - y0) * nx + (cx - x0)
        c = nc[k]
        if c == 0 or (z > zc[k] if highest else z < zc[k]):
            zc[k] = z
        nc[k] = c + 1
    m = 0
    for k in range(nx * ny):
        if nc[k] > 0:
            m += 1
    ix = np.empty(m, np.int64)
    iy = np.empty(m, np.int64)
    z = np.empty(m, np.float64)
    n = np.empty(m, np.int64)
    j = 0
    for k in range(nx * ny):
        if nc[k] > 0:
            ix[j] = k % nx + x0
            iy[j] = k // nx + y0
            z[j] = zc[k]
            n[j] = nc[k]
            j += 1
    return ix, iy, z, n


@nb.njit(cache=True)
def _slot_hash(ix, iy, mask):
    h = ix * 0x7FEB352D + iy * 0x68E31DA5  # int64 arithmetic wraps
    h ^= h >> 29
    h *= 0x2C1B3C6D
    h ^= h >> 32
    return h & mask


@nb.njit(cache=True)
def _grow(a, size):
    out = np.empty(size, a.dtype)
    out[: a.size] = a
    return out


@nb.njit(cache=True)
def hashed_cells(p, cell_m, max_distance, highest):
    """Occupied cells in the order of their first point (memory ~ the occupied cells)."""
    cap = 1 << 12
    ix = np.empty(cap, np.int64)
    iy = np.empty(cap, np.int64)
    zc = np.empty(cap, np.float64)
    nc = np.empty(cap, np.int64)
    mask = 2 * cap - 1
    table = np.full(mask + 1, -1, np.int32)
    m = 0
    last = -1  # slot of the previous point (consecutive points often share a cell)
    for i in range(p.shape[0]):
        used, cx, cy, z = _cell(p, i, cell_m, max_distance)
        if not used:
            continue
        if last >= 0 and ix[last] == cx and iy[last] == cy:
            s = last
        else:
            h = _slot_hash(cx, cy, mask)
            s = table[h]
            while s >= 0 and not (ix[s] == cx and iy[s] == cy):
                h = (h + 1) & mask
                s = table[h]
            if s < 0:
                if m == cap:  # grow the cells and rebuild the table (load <= 1/2)
                    cap *= 2
                    ix, iy = _grow(ix, cap), _grow(iy, cap)
                    zc, nc = _grow(zc, cap), _grow(nc, cap)
                    mask = 2 * cap - 1
                    table = np.full(mask + 1, -1, np.int32)
                    for t in range(m):
                        g = _slot_hash(ix[t], iy[t], mask)
                        while table[g] >= 0:
                            g = (g + 1) & mask
                        table[g] = t
                    h = _slot_hash(cx, cy, mask)
                    while table[h] >= 0:
                        h = (h + 1) & mask
                s = m
                m += 1
                table[h] = s
                ix[s], iy[s], nc[s] = cx, cy, 0
        c = nc[s]
        if c == 0 or (z > zc[s] if highest else z < zc[s]):
            zc[s] = z
        nc[s] = c + 1
        last = s
    return ix[:m].copy(), iy[:m].copy(), zc[:m].copy(), nc[:m].copy()


@nb.njit(cache=True, inline="always")
def _placed(ix, iy, z, k, q, ox, oy, cell_m, pose):
    """Global ``(x, y, z)`` of sample ``q`` of source cell ``k`` (:func:`merged_cells`), with the
    arithmetic of the numpy formulation it replaced."""
    lx = (ix[k] + ox[q]) * cell_m
    ly = (iy[k] + oy[q]) * cell_m
    return pose[0] * lx - pose[1] * ly + pose[2], pose[1] * lx + pose[0] * ly + pose[3], z[k] + pose[4]


@nb.njit(cache=True)
def merged_cells(ix, iy, z, starts, poses, ox, oy, cell_m, highest):
    """Lowest (``highest``: highest) z per global cell of the per-scan elevation cells placed
    with their scans' poses (:func:`~forestmap_assets.core.features.elevation.merge_elevation`):
    cells ``starts[s]:starts[s + 1]`` of ``ix, iy, z`` belong to scan ``s``, whose pose row is
    ``cos h, sin h, x, y, z``; each cell is ``ox, oy`` samples. Returns the grid ``(ny, nx)``
    over the samples' box (NaN: empty) and its origin cell ``gx0, gy0``."""
    gx0 = gy0 = np.iinfo(np.int64).max
    gx1 = gy1 = np.iinfo(np.int64).min
    for s in range(starts.size - 1):
        for k in range(starts[s], starts[s + 1]):
            for q in range(ox.size):
                x, y, _ = _placed(ix, iy, z, k, q, ox, oy, cell_m, poses[s])
                cx, cy = int(math.floor(x / cell_m)), int(math.floor(y / cell_m))
                gx0, gx1, gy0, gy1 = min(gx0, cx), max(gx1, cx), min(gy0, cy), max(gy1, cy)
    if gx1 < gx0:
        return np.full((0, 0), np.nan), 0, 0
    nx, ny = gx1 - gx0 + 1, gy1 - gy0 + 1
    out = np.full(nx * ny, np.nan)
    for s in range(starts.size - 1):
        for k in range(starts[s], starts[s + 1]):
            for q in range(ox.size):
                x, y, zz = _placed(ix, iy, z, k, q, ox, oy, cell_m, poses[s])
                c = (int(math.floor(y / cell_m)) - gy0) * nx + int(math.floor(x / cell_m)) - gx0
                if math.isnan(out[c]) or (zz > out[c] if highest else zz < out[c]):
                    out[c] = zz
    return out.reshape(ny, nx), gx0, gy0
