"""Numba kernels of the spherical projection (spec 1.2, :mod:`forestmap_assets.io.projection`,
:mod:`forestmap_assets.io.angular_grid`): spherical angles, the azimuth origin, exact k nearest
neighbours in the (az, el) plane on a cell grid, the occupancy of a trial grid for the fill
search, the fill ratios and the placement of points into pixels. Each gives the values of the
numpy it replaced bit for bit (same float32/float64 operations and libm functions, same tie
rules; the nearest neighbours up to the order of equal distances) in a few passes over the
points and no temporaries. Work arrays come from a :class:`Scratch` (numpy-allocated and
reused: a fresh page costs microseconds, and a cloud's points come in any order, so a pass
touches every page)."""

from __future__ import annotations

import math

import numba as nb
import numpy as np


class Scratch:
    """Work arrays reused across the kernel calls of one projection, grown as needed."""

    def __init__(self) -> None:
        self._arrays: dict[str, np.ndarray] = {}

    def get(self, name: str, size: int, dtype) -> np.ndarray:
        a = self._arrays.get(name)
        if a is None or a.size < size or a.dtype != dtype:
            a = self._arrays[name] = np.empty(size, dtype)
        return a[:size]


@nb.njit(cache=True)
def hypots(x, y, z, xc, yc, zc, h, r):
    """``h = hypot(x, y)`` and ``r = hypot(h, z)`` (libm's, as numpy's), with contiguous copies
    of ``x, y, z`` (numpy's arctan2 is 3 times faster on them, with the same values): one pass
    over the points."""
    for i in range(x.size):
        xc[i], yc[i], zc[i] = x[i], y[i], z[i]
        h[i] = math.hypot(x[i], y[i])
        r[i] = math.hypot(h[i], z[i])


@nb.njit(cache=True)
def fractions(a, el, off_a, step_a, u0, off_e, step_e, v0, fu, fv):
    """Fractional column ``(a - off_a) / step_a - u0`` and row ``(-el - off_e) / step_e - v0``
    of each point into ``fu, fv`` (the float64 operations of numpy's in-place version)."""
    for i in range(a.size):
        fu[i] = (a[i] - off_a) / step_a - u0
        fv[i] = (-el[i] - off_e) / step_e - v0


@nb.njit(cache=True)
def points_at(r, az_deg, el_deg, out):
    """Points ``r (cos el cos az, cos el sin az, sin el)`` into ``out`` (n, 3): numpy's values
    (libm's sine and cosine; LLVM pairs them into one sincos, 2.5 times faster)."""
    for i in range(r.size):
        az, el = np.radians(az_deg[i]), np.radians(el_deg[i])
        rc = np.float64(r[i]) * math.cos(el)
        out[i, 0] = rc * math.cos(az)
        out[i, 1] = rc * math.sin(az)
        out[i, 2] = r[i] * math.sin(el)


@nb.njit(cache=True)
def azimuth_bins(az, stride, n_bins, width):
    """Counts of every ``stride``-th azimuth in bins ``floor((az + 180) / width) % n_bins``."""
    counts = np.zeros(n_bins, np.int64)
    for i in range(0, az.size, stride):
        counts[int(np.floor((az[i] + 180.0) / width)) % n_bins] += 1
    return counts


@nb.njit(cache=True)
def azimuths_after(az, lo, span):
    """``(az - lo) % 360`` of the azimuths with ``az - lo`` in ``[0, span)`` modulo 360."""
    m = 0
    for i in range(az.size):
        d = az[i] - lo
        m += 0 <= d < span or 360 <= d < 360 + span or -360 <= d < span - 360
    out = np.empty(m)
    m = 0
    for i in range(az.size):
        d = az[i] - lo
        if 0 <= d < span or 360 <= d < 360 + span or -360 <= d < span - 360:
            out[m] = d % 360.0
            m += 1
    return out


@nb.njit(cache=True)
def unwrap(az, origin, out):
    """``out = az - origin``, plus 360 where negative; returns its maximum."""
    hi = -np.inf
    for i in range(az.size):
        a = az[i] - origin
        out[i] = a + 360.0 if a < 0 else a
        hi = max(hi, out[i])
    return hi


@nb.njit(cache=True)
def in_buckets(a, lo, scale, table):
    """Indices of the angles whose bucket ``int((a - lo) * scale)`` is marked in ``table``."""
    m = 0
    for i in range(a.size):
        m += table[int((a[i] - lo) * scale)]
    out = np.empty(m, np.int64)
    m = 0
    for i in range(a.size):
        if table[int((a[i] - lo) * scale)]:
            out[m] = i
            m += 1
    return out


def knn(x, y, q, k, cell):
    """``(len(q), k)`` indices of the ``k`` points nearest (Euclidean) each point ``q[j]``,
    itself included, nearest first (ties: the first found). Points are binned into square cells
    of side ``cell`` (grown until the occupied columns hold at most 4 cells a point), empty
    columns dropped (a few azimuth windows); a query scans rings of cells until its k-th
    distance lies inside them (dropping columns only brings farther points into a ring)."""
    x0, y0 = x.min(), y.min()
    cell = max(cell, float(max(x.max() - x0, y.max() - y0)) / 4000)
    while True:
        cx = ((x - x0) / cell).astype(np.int64)
        cy = ((y - y0) / cell).astype(np.int64)
        used = np.bincount(cx) > 0
        n_cols, n_rows = int(np.count_nonzero(used)), int(cy.max()) + 1
        if n_cols * n_rows <= 4 * x.size + 1024:
            break
        cell *= 2.0
    cx = (np.cumsum(used) - 1)[cx]
    q = np.asarray(q, np.int64)
    keys = cx * n_rows + cy
    return _knn(x, y, cx, cy, n_cols, n_rows, keys, np.zeros(n_cols * n_rows + 1, np.int32), q,
                np.argsort(keys[q], kind="stable"), k, cell)


@nb.njit(cache=True)
def _knn(x, y, cx, cy, nx, ny, keys, start, q, q_order, k, cell):
    for i in range(x.size):  # counting sort by cell: cell c holds order[start[c]:start[c + 1]]
        start[keys[i] + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    order = np.empty(x.size, np.int64)
    for i in range(x.size):
        order[start[keys[i]]] = i
        start[keys[i]] += 1
    for c in range(nx * ny, 0, -1):
        start[c] = start[c - 1]
    start[0] = 0
    xs, ys = x[order], y[order]  # a cell's points side by side in memory
    out = np.empty((q.size, k), np.int64)
    bd = np.empty(k)
    for j in q_order:  # queries cell by cell: their neighbours stay in the cache
        i = q[j]
        found = m = 0
        while True:  # ring m: the cells m columns or rows away
            for gx in range(max(cx[i] - m, 0), min(cx[i] + m, nx - 1) + 1):
                side = abs(gx - cx[i]) == m  # a side column: all its cells in the ring
                for gy in (cy[i] - m, cy[i] + m):  # else its top and bottom cells
                    lo, hi = (max(gy, 0), min(cy[i] + m, ny - 1)) if side else (gy, gy)
                    if lo <= hi and 0 <= lo and hi < ny:
                        found = _offer(j, x[i], y[i], xs, ys, order, start[gx * ny + lo],
                                       start[gx * ny + hi + 1], out, bd, found)
                    if side:
                        break
            reach = m * cell * (1.0 - 1e-9)  # every point this near is in the rings
            if (found == k and bd[k - 1] < reach * reach) or m > nx + ny:
                break
            m += 1
    return out


@nb.njit(cache=True, inline="always")
def _offer(j, qx, qy, xs, ys, order, s, e, out, bd, found):
    """Offer the points ``s:e`` in cell order (``xs, ys``; indices ``order``) to query ``j``'s
    sorted best list (``found`` of ``k`` filled); returns the new count."""
    k = bd.size
    for t in range(s, e):
        dx, dy = xs[t] - qx, ys[t] - qy
        d = dx * dx + dy * dy
        if found == k and d >= bd[k - 1]:
            continue
        p = order[t]
        pos = min(found, k - 1)
        while pos > 0 and bd[pos - 1] > d:
            bd[pos] = bd[pos - 1]
            out[j, pos] = out[j, pos - 1]
            pos -= 1
        bd[pos] = d
        out[j, pos] = p
        found = min(found + 1, k)
    return found


@nb.njit(cache=True, inline="always")
def _within(x, y, limit):
    """``hypot(x, y) <= limit`` (float64; libm's hypot only where the plain root is too near
    ``limit`` to tell: it is 4 times slower)."""
    d2 = x * x + y * y
    if abs(d2 - limit * limit) > 1e-9:
        return d2 < limit * limit
    return math.hypot(x, y) <= limit


@nb.njit(cache=True, inline="always")
def _hypot32(x, y):
    """numpy's float32 ``hypot``: the root of the float64 sum of squares, rounded to float32."""
    return np.float32(math.sqrt(np.float64(x) * np.float64(x) + np.float64(y) * np.float64(y)))


def occupancy(a, el, step_a, step_e, u0, v0, rows, cols, move, scratch):
    """Pixel states (``scratch``'s) of the grid ``u = a / step_a - u0``, ``v = -el / step_e -
    v0`` (the fill search, ``projection._filling_steps``): bits 0-1 the points in the pixel (1,
    2: more), bit 2 filled by a point sharing its pixel: moved to the nearer neighbour on its
    offset's side (beside, else above/below) within ``move`` of its direction (as
    :func:`place` moves points, cheaply)."""
    state = scratch.get("state", rows * cols, np.uint8)
    state[:] = 0
    _occupancy(a, el, step_a, step_e, u0, v0, rows, cols, move, state,
               scratch.get("flat", a.size, np.int32))
    return state


@nb.njit(cache=True)
def _occupancy(a, el, step_a, step_e, u0, v0, rows, cols, move, state, flat):
    n = a.size  # branch-free where it can: the points' order is random
    for i in range(n):
        f = int(np.rint(-el[i] / step_e - v0)) * cols + int(np.rint(a[i] / step_a - u0))
        flat[i] = f
        state[f] += state[f] < 2
    for i in range(n):
        if state[flat[i]] & 3 != 2:
            continue
        fu, fv = a[i] / step_a - u0, -el[i] / step_e - v0
        u, v = np.rint(fu), np.rint(fv)
        du, dv = fu - u, fv - v
        side = abs(du) >= abs(dv)  # the nearer neighbour: beside (else above/below)
        near = _within(1.0 - abs(du) if side else du, dv if side else 1.0 - abs(dv), move)
        off = du if side else dv
        sign = (off > 0) - (off < 0)
        tu, tv = int(u) + (sign if side else 0), int(v) + (0 if side else sign)
        ok = near & (tu >= 0) & (tu < cols) & (tv >= 0) & (tv < rows)
        state[tv * cols + tu if ok else flat[i]] |= 4


@nb.njit(cache=True)
def region_counts(state, rows, cols):
    """Counts of the filled pixels (``state != 0``) and of those in the scanned region (a
    filled one among their 3 x 3), for ``projection.fill_ratio``."""
    n_filled = n_region = 0
    column = np.zeros(cols + 2, np.uint8)  # a row's pixels or-ed with those above and below
    left, mid, right = column[:cols], column[1:cols + 1], column[2:]
    for v in range(rows):  # on row slices (no index arithmetic: it vectorises, 10 x faster)
        above = state[max(v - 1, 0) * cols:max(v - 1, 0) * cols + cols]
        row = state[v * cols:v * cols + cols]
        below = state[min(v + 1, rows - 1) * cols:min(v + 1, rows - 1) * cols + cols]
        for u in range(cols):
            mid[u] = above[u] | row[u] | below[u]
        for u in range(cols):
            n_filled += row[u] != 0
            n_region += (left[u] | mid[u] | right[u]) != 0
    return n_filled, n_region


@nb.njit(cache=True)
def mark(pix, state):
    """``state`` 1 at the pixels ``pix >= 0``, else 0."""
    state[:] = 0
    for p in pix:
        if p >= 0:
            state[p] = 1


@nb.njit(cache=True)
def neighbour_shares(state, rows, cols, n_filled):
    """Per filled pixel (``state != 0``), in pixel order, the share of its neighbours inside
    the image that are filled (``projection.neighbour_fill``)."""
    out = np.empty(n_filled)
    j = 0
    none = np.zeros(cols, np.uint8)
    column = np.zeros(cols + 2, np.uint8)  # filled pixels of a column's 3 rows
    left, mid, right = column[:cols], column[1:cols + 1], column[2:]
    for v in range(rows):  # on row slices, as _occupancy
        above = state[(v - 1) * cols:v * cols] if v > 0 else none
        row = state[v * cols:v * cols + cols]
        below = state[(v + 1) * cols:(v + 2) * cols] if v < rows - 1 else none
        for u in range(cols):
            mid[u] = (above[u] != 0) + (row[u] != 0) + (below[u] != 0)
        n_v = 1 + (v > 0) + (v < rows - 1)
        for u in range(cols):
            if row[u] != 0:
                there = n_v * (1 + (u > 0) + (u < cols - 1)) - 1
                out[j] = (left[u] + mid[u] + right[u] - 1) / there
                j += 1
    return out


def place(fu, fv, r32, rows, cols, front, move, scratch):
    """Pixel (flat index; -1: none; ``scratch``'s) of each point, as ``projection._place``
    describes: per pixel the front point (float32 range ``r32`` within ``front`` of the
    nearest) nearest its centre (float32 ``off^2 + 1e-6 r``; ties: the last point); then, in
    three rounds (the nearest, second and third neighbour on a left-out point's offset side
    within ``move``), each empty pixel takes the nearest of the points aiming at it (ties: the
    last)."""
    n, n_pix = fu.size, rows * cols
    pix = scratch.get("pix", n, np.int32)
    _place(fu, fv, r32, rows, cols, front, move, scratch.get("flat", n, np.int32),
           scratch.get("best", n_pix, np.float32), scratch.get("key", n_pix, np.float32),
           scratch.get("owner", n_pix, np.int32), scratch.get("near", n_pix, np.uint8), pix,
           scratch.get("lose", n, np.int32),
           scratch.get("target", 3 * n, np.int32).reshape(n, 3))
    return pix


@nb.njit(cache=True)
def _place(fu, fv, r32, rows, cols, front, move, flat, best, key_best, owner, near, pix, lose,
           target):
    n = fu.size
    best[:] = np.inf
    key_best[:] = np.inf
    owner[:] = -1  # the point holding a pixel (-1: empty)
    for i in range(n):
        flat[i] = int(np.rint(fv[i])) * cols + int(np.rint(fu[i]))
        best[flat[i]] = min(best[flat[i]], r32[i])
    for i in range(n):  # branch-free: the points' order is random
        f = flat[i]
        du, dv = fu[i] - np.rint(fu[i]), fv[i] - np.rint(fv[i])
        key = np.float32(du * du + dv * dv + np.float64(np.float32(1e-6) * r32[i]))
        better = (r32[i] <= best[f] + front) & (key <= key_best[f])
        key_best[f] = key if better else key_best[f]
        owner[f] = i if better else owner[f]
    # near: the pixels with an empty one among their 3 x 3 (row slices, as region_counts)
    column = np.zeros(cols + 2, np.uint8)
    left, mid, right = column[:cols], column[1:cols + 1], column[2:]
    for v in range(rows):
        above = owner[max(v - 1, 0) * cols:max(v - 1, 0) * cols + cols]
        row = owner[v * cols:v * cols + cols]
        below = owner[min(v + 1, rows - 1) * cols:min(v + 1, rows - 1) * cols + cols]
        for u in range(cols):
            mid[u] = (above[u] < 0) | (row[u] < 0) | (below[u] < 0)
        out = near[v * cols:v * cols + cols]
        for u in range(cols):
            out[u] = left[u] | mid[u] | right[u]
    # the left-out points with an empty pixel among their three targets (a pixel taken now
    # stays taken), the targets nearest first (-1: out of the image, too far or taken)
    n_lose = 0
    one = np.float32(1.0)
    for i in range(n):
        f = flat[i]
        pix[i] = f if owner[f] == i else -1
        if pix[i] >= 0 or near[f] == 0:
            continue
        du, dv = np.float32(fu[i] - np.rint(fu[i])), np.float32(fv[i] - np.rint(fv[i]))
        su, sv = 1 if du >= 0 else -1, 1 if dv >= 0 else -1
        u, v = int(np.rint(fu[i])), int(np.rint(fv[i]))
        in_u, in_v = (u + su >= 0) & (u + su < cols), (v + sv >= 0) & (v + sv < rows)
        # beside, above/below, diagonal; outside the image: the point's own (taken) pixel
        t = (f + su if in_u else f, f + sv * cols if in_v else f,
             f + su + sv * cols if in_u & in_v else f)
        free = (owner[t[0]] < 0, owner[t[1]] < 0, owner[t[2]] < 0)
        if not (free[0] | free[1] | free[2]):
            continue
        d = (_hypot32(one - abs(du), dv), _hypot32(du, one - abs(dv)),
             _hypot32(one - abs(du), one - abs(dv)))
        o0, o1, o2 = 0, 1, 2  # stable sort of the three
        if d[o1] < d[o0]:
            o0, o1 = o1, o0
        if d[o2] < d[o1]:
            o1, o2 = o2, o1
            if d[o1] < d[o0]:
                o0, o1 = o1, o0
        for rank, c in enumerate((o0, o1, o2)):
            target[n_lose, rank] = t[c] if free[c] and d[c] <= move else -1
        lose[n_lose] = i
        n_lose += 1
    # each round: an empty pixel aimed at takes its nearest candidate (ties: the last); it was
    # never aimed at before (every pixel aimed at is taken), so its best range is still inf
    pick = key_best.view(np.int32)
    won = np.zeros(n_lose, np.bool_)
    for rank in range(3):
        for j in range(n_lose):
            t = target[j, rank]
            if not won[j] and t >= 0 and owner[t] < 0 and r32[lose[j]] <= best[t]:
                best[t] = r32[lose[j]]
                pick[t] = j
        for j in range(n_lose):
            t = target[j, rank]
            if not won[j] and t >= 0 and owner[t] < 0 and pick[t] == j:
                pix[lose[j]] = t
                owner[t] = lose[j]
                won[j] = True
    return pix
