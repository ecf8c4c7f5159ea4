"""Numba kernels of the scan-line segmentation (:mod:`~forestmap_assets.core.features.segments`,
spec 2.2-2.4). Each one loops over the image once, with the arithmetic of the numpy formulation
it replaced (float64 pitch ``(r cos el) d_az`` with ``ceil``, float32 ranges and float32 range
steps, float64 ``|r - r_mid|``), so the results are the same bit for bit:

* :func:`occluder_window` - the odd window width of the blocking-object max filter (spec 2.2);
* :func:`max_filter` - the row-wise max over each pixel's window, from a per-row sparse table of
  power-of-two running maxima (only the levels the row's widest window needs);
* :func:`find_runs`, :func:`widen_runs` - runs of the filtered profile and their widening back
  to the outermost returns (spec 2.2 steps 2-3) without whole-image cumulative arrays;
* :func:`inlier_counts` - the T_out gate count of every segment (Eq. 4.7);
* :func:`chain_labels` - vertical chains (spec 2.4) by union-find, numbered by first segment.
"""

from __future__ import annotations

import numba as nb
import numpy as np


def weak_threshold(dtype, value) -> float:
    """``value`` as numpy compares it with an array of ``dtype`` (NEP 50: a Python float is cast
    to the array's float32), returned as the float64 holding that exact value."""
    return float(np.result_type(dtype, value).type(value))


# error_model="numpy": a zero pitch gives inf / nan like numpy instead of raising
@nb.njit(cache=True, error_model="numpy")
def window_px(r, cos_el, daz, occ, maxw):
    """Odd window width at float64 range ``r``: ``ceil(occ / (r cos_el daz) + 1)``, 1 when not
    finite, clipped to [1, maxw] (``np.clip`` order), made odd."""
    pitch = r * cos_el
    pitch *= daz
    x = np.ceil(occ / pitch + 1.0)
    if not np.isfinite(x):
        x = 1.0
    x = min(max(x, 1.0), maxw)
    w = np.int64(x)
    if w % 2 == 0:
        w += 1
    return w


@nb.njit(cache=True, error_model="numpy")
def occluder_window(r, cos_el, daz, occ, maxw):
    """:func:`window_px` of every pixel of the 2-D ``r`` (float32 or float64), ``cos_el[i]``
    being the cosine of row i's elevation."""
    rows, cols = r.shape
    out = np.empty((rows, cols), np.int64)
    for i in range(rows):
        c = cos_el[i]
        for j in range(cols):
            out[i, j] = window_px(np.float64(r[i, j]), c, daz, occ, maxw)
    return out


@nb.njit(cache=True)
def _floor_log2_table(n):
    lg = np.zeros(n + 1, np.int64)
    for k in range(2, n + 1):
        lg[k] = lg[k // 2] + 1
    return lg


@nb.njit(cache=True)
def max_filter(r, window):
    """Row-wise max of the float32 ranges over ``[j - h, j + h]`` (clipped to the row), ``h =
    (window - 1) // 2``; non-finite ranges are left out of the windows and give NaN."""
    rows, cols = r.shape
    out = np.empty((rows, cols), np.float32)
    lg = _floor_log2_table(max(cols, 1))
    table = np.empty((lg[max(cols, 1)] + 1, cols), np.float32)
    hw = np.empty(cols, np.int64)
    for i in range(rows):
        hmax = 0
        for j in range(cols):
            x = r[i, j]
            table[0, j] = np.float32(x) if np.isfinite(x) else np.float32(-np.inf)
            h = max((np.int64(window[i, j]) - 1) // 2, 0)
            hw[j] = h
            hmax = max(hmax, h)
        for k in range(1, lg[min(2 * hmax + 1, cols)] + 1):
            s = 1 << (k - 1)
            for j in range(cols - 2 * s + 1):
                a, b = table[k - 1, j], table[k - 1, j + s]
                table[k, j] = a if a >= b else b
        for j in range(cols):
            if not np.isfinite(r[i, j]):
                out[i, j] = np.nan
                continue
            lo = max(j - hw[j], 0)
            hi = min(j + hw[j], cols - 1)
            k = lg[hi - lo + 1]
            a, b = table[k, lo], table[k, hi - (1 << k) + 1]
            out[i, j] = a if a >= b else b
    return out


@nb.njit(cache=True)
def find_runs(f, step):
    """Flat indices of the first and last pixel of every run of the 2-D float32 profile ``f``:
    consecutive finite pixels of one row with ``|f[j] - f[j-1]| <= step`` (float32 difference)."""
    rows, cols = f.shape
    n = 0
    for i in range(rows):
        for j in range(cols):
            if np.isfinite(f[i, j]) and not (j > 0 and np.isfinite(f[i, j - 1])
                                             and abs(f[i, j] - f[i, j - 1]) <= step):
                n += 1
    starts = np.empty(n, np.int64)
    ends = np.empty(n, np.int64)
    k = -1
    for i in range(rows):
        for j in range(cols):
            if not np.isfinite(f[i, j]):
                continue
            if not (j > 0 and np.isfinite(f[i, j - 1]) and abs(f[i, j] - f[i, j - 1]) <= step):
                k += 1
                starts[k] = i * cols + j
            ends[k] = i * cols + j
    return starts, ends


@nb.njit(cache=True)
def widen_runs(v, cols, row, s_col, e_col, hw):
    """Run ``[s_col, e_col]`` of ``row`` widened by ``hw`` on each side, clipped to the row and
    then to the first / last finite pixel of the flat image ``v`` (never inside the run), and
    the count of finite pixels in the widened run."""
    m = row.size
    c0 = np.empty(m, np.int64)
    c1 = np.empty(m, np.int64)
    cnt = np.empty(m, np.int64)
    for k in range(m):
        base = row[k] * cols
        t = base + max(s_col[k] - hw[k], 0)
        while t < base + s_col[k] and not np.isfinite(v[t]):
            t += 1
        a = min(t - base, s_col[k])
        t = base + min(e_col[k] + hw[k], cols - 1)
        while t > base + e_col[k] and not np.isfinite(v[t]):
            t -= 1
        b = max(t - base, e_col[k])
        c = 0
        for t in range(base + a, base + b + 1):
            c += np.isfinite(v[t])
        for t in range(base + b + 1, base + a):  # prefix-sum difference if ever b < a - 1
            c -= np.isfinite(v[t])
        c0[k], c1[k], cnt[k] = a, b, c
    return c0, c1, cnt


@nb.njit(cache=True)
def inlier_counts(r, row, c0, c1, r_mid, t_out):
    """Pixels of each interval ``[c0, c1]`` of ``row`` with ``|r - r_mid| <= t_out`` (float64)."""
    out = np.zeros(row.size, np.int64)
    for k in range(row.size):
        n = 0
        for c in range(c0[k], c1[k] + 1):
            if abs(np.float64(r[row[k], c]) - r_mid[k]) <= t_out[k]:
                n += 1
        out[k] = n
    return out


@nb.njit(cache=True)
def _find(parent, a):
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@nb.njit(cache=True)
def chain_labels(row, c0, c1, rm, step, order):
    """Connected components of the segments linked when in adjacent rows with overlapping
    ``[c0, c1]`` and ``|rm[b] - rm[a]| <= step``, numbered in order of their first segment.
    ``order`` sorts the segments by (row, c0)."""
    n = row.size
    parent = np.arange(n)
    # groups of one row in ``order``, with their widest span
    g_lo = np.empty(n + 1, np.int64)
    g_row = np.empty(n, np.int64)
    g_span = np.empty(n, np.int64)
    g_of = np.empty(n, np.int64)
    ng = 0
    for t in range(n):
        s = order[t]
        if t == 0 or row[s] != g_row[ng - 1]:
            g_lo[ng] = t
            g_row[ng] = row[s]
            g_span[ng] = 0
            ng += 1
        g_span[ng - 1] = max(g_span[ng - 1], c1[s] - c0[s])
        g_of[s] = ng - 1
    g_lo[ng] = n
    for a in range(n):
        g = g_of[a] + 1
        if g >= ng or g_row[g] != row[a] + 1:
            continue
        # first segment of the next row that can reach c0[a]: c0 >= c0[a] - span (binary search)
        lo, hi = g_lo[g], g_lo[g + 1]
        x = c0[a] - g_span[g]
        while lo < hi:
            mid = (lo + hi) // 2
            if c0[order[mid]] < x:
                lo = mid + 1
            else:
                hi = mid
        for t in range(lo, g_lo[g + 1]):
            b = order[t]
            if c0[b] > c1[a]:
                break
            if c1[b] >= c0[a] and abs(rm[b] - rm[a]) <= step:
                ra, rb = _find(parent, a), _find(parent, b)
                if ra != rb:
                    parent[max(ra, rb)] = min(ra, rb)
    lab = np.empty(n, np.int64)
    num = np.full(n, -1, np.int64)
    nxt = 0
    for a in range(n):
        r = _find(parent, a)
        if num[r] < 0:
            num[r] = nxt
            nxt += 1
        lab[a] = num[r]
    return lab
