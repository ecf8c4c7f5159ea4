"""Numba kernels that place a cloud's points into the pixels of its range image and write the
image (spec 1.2, :func:`forestmap_assets.io.projection.project_angles`), on every core.

A point's fractional column ``(a - off_a) / step_a - u0`` and row ``(-el - off_e) / step_e -
v0`` are recomputed where needed (a division is cheaper than a pass over two float64 arrays,
and a fresh page costs more than both). The passes that pick a pixel's point go over the points
in their order in each of a few bands of pixel rows, one band a thread, so the ties fall as
in one serial pass, whatever the number of threads; the other passes write each point's own
outputs. The values are those of the serial kernels they replace, bit for bit."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

_BLOCK = 1 << 14  # points per parallel task
_KEYS = 1 << 11  # points whose keys are computed at once


@nb.njit(cache=True, inline="always", error_model="numpy")
def _frac(a, el, off_a, step_a, u0, off_e, step_e, v0):
    return (a - off_a) / step_a - u0, (-el - off_e) / step_e - v0


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _pixel_of(a, el, off_a, step_a, u0, off_e, step_e, v0, cols, flat):
    """Each point's pixel (flat index, the nearest centre) into ``flat``."""
    for i in nb.prange(a.size):
        fu, fv = _frac(a[i], el[i], off_a, step_a, u0, off_e, step_e, v0)
        flat[i] = int(np.rint(fv)) * cols + int(np.rint(fu))


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _front(flat, a, el, off_a, step_a, u0, off_e, step_e, v0, r32, front, edges, best,
           key_best, owner):
    """Per pixel the nearest range ``best``, then the point holding it (``owner``; -1: none):
    the front point (within ``front`` of ``best``) nearest the pixel's centre (float32 key
    ``off^2 + 1e-6 r``; ties: the last point); thread ``t`` takes the pixels
    ``edges[t]:edges[t + 1]``, the keys of a block of points computed at once (vectorised)."""
    n = flat.size
    for t in nb.prange(edges.size - 1):
        lo, hi = edges[t], edges[t + 1]
        best[lo:hi] = np.inf
        key_best[lo:hi] = np.inf
        owner[lo:hi] = -1
        for i in range(n):
            f = flat[i]
            if lo <= f < hi:
                best[f] = min(best[f], r32[i])
        keys = np.empty(_KEYS, np.float32)
        for s in range(0, n, _KEYS):
            e = min(n, s + _KEYS)
            mine = 0
            for i in range(s, e):
                mine += (lo <= flat[i]) & (flat[i] < hi)
            if mine == 0:
                continue
            for i in range(s, e):
                fu, fv = _frac(a[i], el[i], off_a, step_a, u0, off_e, step_e, v0)
                du, dv = fu - np.rint(fu), fv - np.rint(fv)
                keys[i - s] = np.float32(du * du + dv * dv + np.float64(np.float32(1e-6) * r32[i]))
            for i in range(s, e):
                f = flat[i]
                if lo <= f < hi and r32[i] <= best[f] + front and keys[i - s] <= key_best[f]:
                    key_best[f] = keys[i - s]
                    owner[f] = i


@nb.njit(cache=True, parallel=True)
def _near(owner, rows, cols, near):
    """``near``: the pixels with an empty one among their 3 x 3 (on row slices, as
    ``region_counts``; bands of rows in parallel)."""
    n_bands = min(rows, 64)
    for b in nb.prange(n_bands):
        column = np.zeros(cols + 2, np.uint8)
        left, mid, right = column[:cols], column[1:cols + 1], column[2:]
        for v in range(b * rows // n_bands, (b + 1) * rows // n_bands):
            above = owner[max(v - 1, 0) * cols:max(v - 1, 0) * cols + cols]
            row = owner[v * cols:v * cols + cols]
            below = owner[min(v + 1, rows - 1) * cols:min(v + 1, rows - 1) * cols + cols]
            for u in range(cols):
                mid[u] = (above[u] < 0) | (row[u] < 0) | (below[u] < 0)
            out = near[v * cols:v * cols + cols]
            for u in range(cols):
                out[u] = left[u] | mid[u] | right[u]


@nb.njit(cache=True, inline="always")
def _hypot32(x, y):
    """numpy's float32 ``hypot``: the root of the float64 sum of squares, rounded to float32."""
    return np.float32(math.sqrt(np.float64(x) * np.float64(x) + np.float64(y) * np.float64(y)))


@nb.njit(cache=True, inline="always", error_model="numpy")
def _targets(f, fu, fv, rows, cols, owner, move):
    """The three pixels a point left out of pixel ``f`` may fill (beside, above/below,
    diagonal on its offset's side), nearest first (-1: out of the image, farther than ``move``
    or taken), and whether any of them is empty."""
    one = np.float32(1.0)
    du, dv = np.float32(fu - np.rint(fu)), np.float32(fv - np.rint(fv))
    su, sv = 1 if du >= 0 else -1, 1 if dv >= 0 else -1
    u, v = int(np.rint(fu)), int(np.rint(fv))
    in_u, in_v = (u + su >= 0) & (u + su < cols), (v + sv >= 0) & (v + sv < rows)
    # outside the image: the point's own (taken) pixel
    t = (f + su if in_u else f, f + sv * cols if in_v else f,
         f + su + sv * cols if in_u & in_v else f)
    free = (owner[t[0]] < 0, owner[t[1]] < 0, owner[t[2]] < 0)
    d = (_hypot32(one - abs(du), dv), _hypot32(du, one - abs(dv)),
         _hypot32(one - abs(du), one - abs(dv)))
    o0, o1, o2 = 0, 1, 2  # stable sort of the three
    if d[o1] < d[o0]:
        o0, o1 = o1, o0
    if d[o2] < d[o1]:
        o1, o2 = o2, o1
        if d[o1] < d[o0]:
            o0, o1 = o1, o0
    return (t[o0] if free[o0] and d[o0] <= move else -1,
            t[o1] if free[o1] and d[o1] <= move else -1,
            t[o2] if free[o2] and d[o2] <= move else -1, free[0] | free[1] | free[2])


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _left_out(pix, a, el, off_a, step_a, u0, off_e, step_e, v0, rows, cols, owner, near, move,
              counts):
    """``pix``: each point's pixel if it holds it, ``-2 - pixel`` if it is left out with an
    empty pixel among its :func:`_targets` (next to an empty one: ``near``), else -1 (``pix``
    holds the points' pixels on entry); ``counts``: the points left out per block."""
    n = pix.size
    for b in nb.prange(counts.size):
        k = 0
        for i in range(b * _BLOCK, min(n, (b + 1) * _BLOCK)):
            f = pix[i]
            if owner[f] == i:
                continue
            pix[i] = -1
            if near[f] == 0:
                continue
            fu, fv = _frac(a[i], el[i], off_a, step_a, u0, off_e, step_e, v0)
            if _targets(f, fu, fv, rows, cols, owner, move)[3]:
                pix[i] = -2 - f
                k += 1
        counts[b] = k


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _losers(pix, a, el, off_a, step_a, u0, off_e, step_e, v0, rows, cols, owner, move, start,
            lose, target):
    """The points :func:`_left_out` marked, in order, into ``lose`` (their ``pix`` back to -1)
    and their targets into ``target``; block ``b``'s from ``start[b]`` on."""
    n = pix.size
    for b in nb.prange(start.size - 1):
        m = start[b]
        for i in range(b * _BLOCK, min(n, (b + 1) * _BLOCK)):
            if pix[i] > -2:
                continue
            f = -2 - pix[i]
            pix[i] = -1
            fu, fv = _frac(a[i], el[i], off_a, step_a, u0, off_e, step_e, v0)
            t0, t1, t2, _ = _targets(f, fu, fv, rows, cols, owner, move)
            target[m, 0] = t0
            target[m, 1] = t1
            target[m, 2] = t2
            lose[m] = i
            m += 1


@nb.njit(cache=True)
def _rounds(lose, target, r32, best, pick, owner, pix):
    """The left-out points fill empty pixels in three rounds (nearest, second, third target):
    each empty pixel aimed at takes the nearest of its candidates (ties: the last); it was
    never aimed at before (every pixel aimed at is taken), so its best range is still inf."""
    n_lose = lose.size
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


def place(a, el, grid, r32, rows, cols, front, move, scratch):
    """Pixel (flat index; -1: none; ``scratch``'s) of each point at unwrapped azimuth ``a``
    and elevation ``el`` on ``grid = (off_a, step_a, u0, off_e, step_e, v0)``, as
    ``projection._place`` describes: per pixel the front point (float32 range ``r32`` within
    ``front`` of the nearest) nearest its centre (float32 ``off^2 + 1e-6 r``; ties: the last
    point); then, in three rounds (the nearest, second and third neighbour on a left-out
    point's offset side within ``move``), each empty pixel takes the nearest of the points
    aiming at it (ties: the last)."""
    n, n_pix = a.size, rows * cols
    pix = scratch.get("pix", n, np.int32)
    best, key_best = scratch.get("best", n_pix, np.float32), scratch.get("key", n_pix, np.float32)
    owner, near = scratch.get("owner", n_pix, np.int32), scratch.get("near", n_pix, np.uint8)
    n_bands = max(1, min(nb.get_num_threads(), rows))
    edges = np.array([(t * rows // n_bands) * cols for t in range(n_bands + 1)], np.int64)
    _pixel_of(a, el, *grid, cols, pix)
    _front(pix, a, el, *grid, r32, front, edges, best, key_best, owner)
    _near(owner, rows, cols, near)
    counts = np.zeros((n + _BLOCK - 1) // _BLOCK, np.int64)
    _left_out(pix, a, el, *grid, rows, cols, owner, near, move, counts)
    start = np.concatenate(([0], np.cumsum(counts)))
    lose, target = np.empty(start[-1], np.int32), np.empty((start[-1], 3), np.int32)
    _losers(pix, a, el, *grid, rows, cols, owner, move, start, lose, target)
    _rounds(lose, target, r32, best, key_best.view(np.int32), owner, pix)
    return pix


@nb.njit(cache=True, parallel=True, error_model="numpy")
def write_image(pix, r, a, el, origin, intensity, rgb, range_img, int_img, rgb_img, points):
    """The image of the placed points (``pix``): range (float32), intensity (``int_img``, if
    it has pixels), colour (``rgb_img``, if it has pixels) and each point's own xyz ``r (cos el
    cos az, cos el sin az, sin el)`` at azimuth ``a + origin`` (float64, then float32; libm's
    sine and cosine: LLVM pairs them into one sincos, numpy's values)."""
    has_int, has_rgb = int_img.size > 0, rgb_img.size > 0
    for i in nb.prange(pix.size):
        p = pix[i]
        if p < 0:
            continue
        range_img[p] = r[i]
        az, e = np.radians(a[i] + origin), np.radians(el[i])
        rc = np.float64(r[i]) * math.cos(e)
        points[p, 0] = rc * math.cos(az)
        points[p, 1] = rc * math.sin(az)
        points[p, 2] = r[i] * math.sin(e)
        if has_int:
            int_img[p] = intensity[i]
        if has_rgb:
            for c in range(3):
                rgb_img[p, c] = rgb[i, c]


@nb.njit(cache=True, parallel=True)
def fill(out, value):
    """``out[:] = value`` (flat), in parallel: a new image's pages are first touched by every
    core."""
    n = out.size
    for b in nb.prange((n + _BLOCK - 1) // _BLOCK):
        out[b * _BLOCK:min(n, (b + 1) * _BLOCK)] = value


@nb.njit(cache=True, parallel=True)
def bridge_rows(range_img, intensity, rgb, points, max_gap, tol):
    """``readers_common.bridge_row_gaps`` row by row (rows in parallel): gaps of 1, then 2, ...
    ``max_gap`` pixels empty at the start, between two returns less than ``tol`` apart
    (float32), filled in float32 as numpy does. A pixel filled is never the end of a longer
    gap (its neighbours held returns), so a row done in order gives the values of the
    vectorised passes. ``intensity``, ``rgb``, ``points``: empty when the image has none."""
    rows, cols = range_img.shape
    one = np.float32(1.0)
    for v in nb.prange(rows):
        empty = np.empty(cols, np.bool_)
        for u in range(cols):
            empty[u] = not np.isfinite(range_img[v, u])
        for g in range(1, max_gap + 1):
            for u in range(cols - g - 1):
                if not abs(range_img[v, u] - range_img[v, u + g + 1]) <= tol:
                    continue
                gap = True
                for k in range(g):
                    gap &= empty[u + 1 + k]
                if not gap:
                    continue
                e = u + g + 1
                for k in range(g):
                    w = np.float32((k + 1) / (g + 1))
                    t = u + 1 + k
                    range_img[v, t] = (one - w) * range_img[v, u] + w * range_img[v, e]
                    if intensity.size:
                        intensity[v, t] = (one - w) * intensity[v, u] + w * intensity[v, e]
                    if points.size:
                        for c in range(3):
                            points[v, t, c] = (one - w) * points[v, u, c] + w * points[v, e, c]
                    if rgb.size:
                        for c in range(3):
                            rgb[v, t, c] = rgb[v, u if w <= 0.5 else e, c]
