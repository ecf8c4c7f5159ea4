"""Numba kernels of :func:`~forestmap_assets.core.cloud.voxel_subsample` (spec 3.2) and
:func:`~forestmap_assets.core.cloud.z_order`, the radix sort they (and the observed surface's
voxels, :mod:`~forestmap_assets.core.exploration.surface`) order their keys with, and the
cloud's crop and placement from a stored range image's columns. The voxel subsample numbers
the voxels, then makes one pass over the points sorted voxel by voxel, with the arithmetic of
the numpy formulation it replaced (``floor((p - origin) / voxel_m)``, centroid summed in input
order, squared distance over ``voxel_m^2`` rounded to 9 decimals), so the representatives are
the same (finite points). The subsample's kernels release the GIL, so that the scans of the
registered cloud are thinned in threads (:mod:`forestmap_assets.core.mapping.point_cloud`)."""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(cache=True)
def bounds(p):
    """``(p.min(axis=0), p.max(axis=0), np.isfinite(p).all())`` of ``p`` (n >= 1, 3) in one pass
    over the rows (numpy's reductions along the first axis of an (n, 3) array took 9 ms each on
    320,000 points; issue 16)."""
    lo, hi = p[0].copy(), p[0].copy()
    finite = True
    for i in range(p.shape[0]):
        for a in range(3):
            v = p[i, a]
            finite &= math.isfinite(v)
            lo[a] = min(lo[a], v)
            hi[a] = max(hi[a], v)
    return lo, hi, finite


@nb.njit(cache=True, nogil=True)
def placed_points(x, y, z, pose):
    """Points (n, 3) float64 of the columns ``x, y, z`` placed with ``pose`` (x, y, z,
    heading_deg; spec 6.1: ``p' = R_z(heading) p + t``), in one pass: what
    :func:`~forestmap_assets.core.geometry.transform_points` gives (to the last bit or two)
    without a float64 copy of the columns first."""
    h = math.radians(pose[3])
    c, s = math.cos(h), math.sin(h)
    out = np.empty((x.shape[0], 3), np.float64)
    for i in range(x.shape[0]):
        a, b = np.float64(x[i]), np.float64(y[i])
        out[i, 0] = c * a - s * b + pose[0]
        out[i, 1] = s * a + c * b + pose[1]
        out[i, 2] = np.float64(z[i]) + pose[2]
    return out


@nb.njit(cache=True, nogil=True)
def cropped_points(x, y, z, max_range, z_lo, z_hi):
    """Points (m, 3) float64 of the columns ``x, y, z`` within ``max_range`` of the sensor's
    vertical axis and with ``z_lo <= z <= z_hi``, in input order, in one pass: the rows of the
    float64 points that ``(sqrt(x^2 + y^2) <= max_range) & (z >= z_lo) & (z <= z_hi)`` keeps,
    without a float64 copy of the whole cloud and its temporaries first (the same IEEE
    arithmetic: no fused multiply-add without fastmath)."""
    out = np.empty((x.shape[0], 3), np.float64)
    m = 0
    for i in range(x.shape[0]):
        a, b, c = np.float64(x[i]), np.float64(y[i]), np.float64(z[i])
        if math.sqrt(a * a + b * b) <= max_range and c >= z_lo and c <= z_hi:
            out[m, 0] = a
            out[m, 1] = b
            out[m, 2] = c
            m += 1
    return out[:m]


@nb.njit(cache=True, nogil=True)
def finite_rows(p):
    """Indices of the rows of ``p`` (n, 3) whose three values are finite, in one pass."""
    out = np.empty(p.shape[0], np.int64)
    n = 0
    for i in range(p.shape[0]):
        if np.isfinite(p[i, 0]) and np.isfinite(p[i, 1]) and np.isfinite(p[i, 2]):
            out[n] = i
            n += 1
    return out[:n]


@nb.njit(cache=True, nogil=True)
def voxel_numbers(p, voxel_m, origin):
    """Row-major number of each point's voxel (edge ``voxel_m``, anchored at ``origin``) in the
    box of the occupied voxels. Two passes over the points, the voxel indices computed again in
    the second rather than kept (an (n, 3) int64 array: 42 MB for 1.75 M points)."""
    n = p.shape[0]
    kmin = np.full(3, np.iinfo(np.int64).max)
    kmax = np.full(3, np.iinfo(np.int64).min)
    for i in range(n):
        for a in range(3):
            k = int(math.floor((p[i, a] - origin[a]) / voxel_m))
            kmin[a] = min(kmin[a], k)
            kmax[a] = max(kmax[a], k)
    ny, nz = kmax[1] - kmin[1] + 1, kmax[2] - kmin[2] + 1
    flat = np.empty(n, np.int64)
    for i in range(n):
        kx = int(math.floor((p[i, 0] - origin[0]) / voxel_m)) - kmin[0]
        ky = int(math.floor((p[i, 1] - origin[1]) / voxel_m)) - kmin[1]
        kz = int(math.floor((p[i, 2] - origin[2]) / voxel_m)) - kmin[2]
        flat[i] = (kx * ny + ky) * nz + kz
    return flat


@nb.njit(cache=True, nogil=True)
def voxel_representatives(p, order, flat, voxel_m, origin):
    """Input rows of the representative of each voxel: ``order`` lists the rows voxel by voxel
    (stable: each voxel's points in input order), ``flat`` their voxel numbers in that order.
    The representative is the point nearest the voxel's centroid; ties (the two points of every
    two-point voxel) go to the point nearest the voxel's centre (``origin``: the grid's corner),
    which favours no direction, then to the lexicographically smallest point, then to the first
    in input order. (Ties to the lexicographically smallest point moved every two-point voxel's
    representative toward -x, by half the pair's x spacing: a displacement of each scan's
    thinned cloud along its own x axis.)"""
    n = len(order)
    out = np.empty(n, np.int64)
    v2 = voxel_m * voxel_m
    nv = 0
    s = 0
    while s < n:
        e = s + 1
        while e < n and flat[e] == flat[s]:
            e += 1
        cx = cy = cz = 0.0
        for t in range(s, e):
            cx += p[order[t], 0]
            cy += p[order[t], 1]
            cz += p[order[t], 2]
        cx, cy, cz = cx / (e - s), cy / (e - s), cz / (e - s)
        i0 = order[s]  # the voxel's centre, from its first point
        gx = origin[0] + (math.floor((p[i0, 0] - origin[0]) / voxel_m) + 0.5) * voxel_m
        gy = origin[1] + (math.floor((p[i0, 1] - origin[1]) / voxel_m) + 0.5) * voxel_m
        gz = origin[2] + (math.floor((p[i0, 2] - origin[2]) / voxel_m) + 0.5) * voxel_m
        best = order[s]
        bd = np.inf
        bg = np.inf
        for t in range(s, e):
            i = order[t]
            x, y, z = p[i, 0], p[i, 1], p[i, 2]
            d = np.rint(((x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2) / v2 * 1e9) / 1e9
            g = ((x - gx) ** 2 + (y - gy) ** 2 + (z - gz) ** 2) / v2
            b = p[best]
            if d < bd or (d == bd and (g < bg or (g == bg and (
                    x < b[0] or (x == b[0] and (y < b[1] or (y == b[1] and z < b[2]))))))):
                best, bd, bg = i, d, g
        out[nv] = best
        nv += 1
        s = e
    return out[:nv]


@nb.njit(cache=True, inline="always")
def _spread_bits(v):
    """The low 21 bits of ``v`` spread to every third bit."""
    v &= 0x1FFFFF
    v = (v | (v << 32)) & 0x1F00000000FFFF
    v = (v | (v << 16)) & 0x1F0000FF0000FF
    v = (v | (v << 8)) & 0x100F00F00F00F00F
    v = (v | (v << 4)) & 0x10C30C30C30C30C3
    return (v | (v << 2)) & 0x1249249249249249


@nb.njit(cache=True)
def morton_codes(p):
    """63-bit Morton (Z-order) codes of the points in their bounding box, 2^21 cells per axis."""
    lo, hi, _ = bounds(p)
    step = max(max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) / 0x1FFFFF, 1e-300)
    code = np.empty(p.shape[0], np.int64)
    for i in range(p.shape[0]):
        c = 0
        for a in range(3):
            c |= _spread_bits(min(int(math.floor((p[i, a] - lo[a]) / step)), 0x1FFFFF)) << a
        code[i] = c
    return code


@nb.njit(cache=True, nogil=True)
def radix_sort(keys, bits, with_index):
    """Non-negative int64 ``keys`` below ``2**bits`` sorted by an LSD radix sort of 11-bit
    digits (every digit's histogram in one read; a digit all keys share is skipped), and with
    ``with_index`` the stable order's indices carried beside them (else an empty array):
    ``(sorted keys, indices)``. ``keys`` is used as a buffer."""
    n = keys.size
    n_digits = max((bits + 10) // 11, 1)
    count = np.zeros((n_digits, 2049), np.int64)
    for i in range(n):
        k = keys[i]
        for d in range(n_digits):
            count[d, ((k >> (11 * d)) & 2047) + 1] += 1
    key, key2 = keys, np.empty_like(keys)
    idx = np.arange(n) if with_index else np.empty(0, np.int64)
    idx2 = np.empty_like(idx)
    for d in range(n_digits):
        offset = count[d]
        if offset.max() == n:  # one bucket holds every key: this digit leaves the order
            continue
        for b in range(2048):
            offset[b + 1] += offset[b]
        shift = 11 * d
        for i in range(n):
            b = (key[i] >> shift) & 2047
            j = offset[b]
            key2[j] = key[i]
            if with_index:
                idx2[j] = idx[i]
            offset[b] = j + 1
        key, key2 = key2, key
        idx, idx2 = idx2, idx
    return key, idx


@nb.njit(cache=True, nogil=True)
def stable_argsort(keys, max_key):
    """``np.argsort(keys, kind="stable")`` of non-negative int64 ``keys`` up to ``max_key`` by
    :func:`radix_sort` (as many passes as ``max_key`` has 11-bit digits: 3 for the 5 cm voxels
    of a scan's 40 m box, where numpy's sort of 1.5 M composite keys took 60-90 ms)."""
    return stable_sort(keys.copy(), max_key)[1]


@nb.njit(cache=True, nogil=True)
def stable_sort(keys, max_key):
    """:func:`stable_argsort` and the sorted keys beside it, ``keys`` used up as the sort's
    buffer: ``(sorted keys, order)`` (no copy of the keys and no gather of them in the order)."""
    bits = 1
    while bits < 63 and (np.int64(1) << bits) <= max_key:
        bits += 1
    return radix_sort(keys, bits, True)
