"""Numba kernels of the spherical projection (spec 1.2, :mod:`forestmap_assets.io.projection`,
:mod:`forestmap_assets.io.angular_grid`): the points' validity, the azimuth origin and the
unwrapped azimuths, exact k nearest neighbours in the (az, el) plane on a cell grid, the
occupancy of a trial grid for the fill search and the fill ratios (the hypots are in
:mod:`._cloud_kernels`, the placement of points into pixels in :mod:`._place_kernels`). Each
gives the values of the numpy it replaced bit for bit (same float32/float64 operations and libm
functions, same tie rules; the nearest neighbours up to the order of equal distances) in a few
passes over the points and no temporaries; the passes over all points run on every core, in
blocks whose results are combined in block order. Work arrays come from a :class:`Scratch`
(allocated once and reused: a fresh page costs microseconds, and a cloud's points come in any
order, so a pass touches every page)."""

from __future__ import annotations

import contextlib
import math
import mmap
import warnings

import numba as nb
import numpy as np

_BLOCK = 1 << 14  # points per parallel task


@nb.njit(cache=True, parallel=True)
def _touch(a):
    for i in nb.prange(a.size):
        a[i] = i


_THREADS: list[bool] = []


@contextlib.contextmanager
def without_tbb_warning():
    """Starting numba's thread pool warns about the older TBB that open3d loads (numba falls back
    to OpenMP); this leaves the warning out."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*TBB threading layer.*")
        yield


def start_threads() -> None:
    """Start numba's thread pool (once, before the first parallel kernel), quietly."""
    if not _THREADS:
        with without_tbb_warning():
            _touch(np.zeros(2))
        _THREADS.append(True)


def small_pages(n: int, dtype, *shape: int) -> np.ndarray:
    """``np.empty((n, *shape), dtype)`` on 4 KB pages (an anonymous mmap), for a big array
    written and read in order: numpy asks for huge pages for big arrays, and on a VM that hands
    freed memory back to its host (here) a fresh huge page costs 2-3 times more than its 512
    small ones (1-2.5 s a GB)."""
    count = n * math.prod(shape)
    size = count * np.dtype(dtype).itemsize
    return np.frombuffer(mmap.mmap(-1, max(size, 1)), dtype, count).reshape(n, *shape)


class Scratch:
    """Work arrays reused across the kernel calls of one projection, grown as needed (those
    named in ``in_order`` on :func:`small_pages`)."""

    def __init__(self, in_order: tuple[str, ...] = ("pix",)) -> None:
        self._arrays: dict[str, np.ndarray] = {}
        self._in_order = in_order

    def get(self, name: str, size: int, dtype) -> np.ndarray:
        a = self._arrays.get(name)
        if a is None or a.size < size or a.dtype != dtype:
            new = small_pages if name in self._in_order else np.empty
            a = self._arrays[name] = new(size, dtype)
        return a[:size]


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


@nb.njit(cache=True, parallel=True)
def min_after(az, lo, span):
    """The least ``(az - lo) % 360`` of the azimuths with ``az - lo`` in ``[0, span)`` modulo
    360 (inf: none): ``azimuths_after(az, lo, span).min()`` in one parallel pass."""
    n_blocks = (az.size + _BLOCK - 1) // _BLOCK
    least = np.full(n_blocks, np.inf)
    for b in nb.prange(n_blocks):
        m = np.inf
        for i in range(b * _BLOCK, min(az.size, (b + 1) * _BLOCK)):
            d = az[i] - lo
            if 0 <= d < span or 360 <= d < 360 + span or -360 <= d < span - 360:
                m = min(m, d % 360.0)
        least[b] = m
    return least.min()


@nb.njit(cache=True, parallel=True)
def unwrap(az, origin, out):
    """``out = az - origin``, plus 360 where negative (``out`` may be ``az``); returns its
    minimum and maximum."""
    n_blocks = (az.size + _BLOCK - 1) // _BLOCK
    lo, hi = np.full(n_blocks, np.inf), np.full(n_blocks, -np.inf)
    for b in nb.prange(n_blocks):
        mn, mx = np.inf, -np.inf
        for i in range(b * _BLOCK, min(az.size, (b + 1) * _BLOCK)):
            a = az[i] - origin
            a = a + 360.0 if a < 0 else a
            out[i] = a
            mn, mx = min(mn, a), max(mx, a)
        lo[b], hi[b] = mn, mx
    return lo.min(), hi.max()


@nb.njit(cache=True, parallel=True)
def min_max(a):
    """``a.min(), a.max()`` (NaN if any is) in one parallel pass."""
    n_blocks = (a.size + _BLOCK - 1) // _BLOCK
    lo, hi = np.full(n_blocks, np.inf), np.full(n_blocks, -np.inf)
    for b in nb.prange(n_blocks):
        mn, mx = np.inf, -np.inf
        for i in range(b * _BLOCK, min(a.size, (b + 1) * _BLOCK)):
            mn, mx = min(mn, a[i]), max(mx, a[i])
            if a[i] != a[i]:
                mn = mx = np.nan
                break
        lo[b], hi[b] = mn, mx
    for b in range(n_blocks):
        if lo[b] != lo[b]:
            return np.nan, np.nan
    return lo.min(), hi.max()


@nb.njit(cache=True, parallel=True)
def count_valid(r, az, el):
    """The points with a finite positive range and finite angles."""
    n_blocks = (r.size + _BLOCK - 1) // _BLOCK
    counts = np.zeros(n_blocks, np.int64)
    for b in nb.prange(n_blocks):
        k = 0
        for i in range(b * _BLOCK, min(r.size, (b + 1) * _BLOCK)):
            k += (r[i] > 0) & (r[i] < np.inf) & np.isfinite(az[i]) & np.isfinite(el[i])
        counts[b] = k
    return counts.sum()


@nb.njit(cache=True, parallel=True)
def in_buckets(a, lo, scale, table):
    """Indices of the angles whose bucket ``int((a - lo) * scale)`` is marked in ``table``, in
    order: in parallel, blocks marked in a bit mask and counted, then filled from the mask (one
    pass over the angles)."""
    n_blocks = (a.size + _BLOCK - 1) // _BLOCK
    mask = np.zeros((a.size + 63) // 64, np.uint64)
    start = np.zeros(n_blocks + 1, np.int64)
    for b in nb.prange(n_blocks):
        k = 0
        for i in range(b * _BLOCK, min(a.size, (b + 1) * _BLOCK)):
            if table[int((a[i] - lo) * scale)]:
                mask[i >> 6] |= np.uint64(1) << np.uint64(i & 63)
                k += 1
        start[b + 1] = k
    for b in range(n_blocks):
        start[b + 1] += start[b]
    out = np.empty(start[n_blocks], np.int64)
    for b in nb.prange(n_blocks):
        m = start[b]
        for w in range(b * _BLOCK // 64, min(mask.size, (b + 1) * _BLOCK // 64)):
            bits = mask[w]
            while bits:
                j = 0
                while not (bits >> np.uint64(j)) & np.uint64(1):
                    j += 1
                out[m] = w * 64 + j
                m += 1
                bits &= bits - np.uint64(1)
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
