"""Numba kernels of the occlusion detector and the observed surface (men_spec 3.1,
:mod:`.occlusion`, :mod:`.surface`): the tests of every neighbouring pair with the pixel masks
spread from them, the columns of the boundary table, and the voxel keys of the returns and
gap-fill samples with their counts. Each reproduces the numpy it replaced bit for bit (same
float64 operations in the same order) without its full-image temporaries.

A pixel's levelled point comes from ``xyz`` (rows, cols, 3), float32 or float64, or, when
``xyz`` is empty, from its range and the ray trigonometry ``trig = (cos az, sin az, cos el,
sin el)`` as :func:`~forestmap_assets.core.features.range_image.spherical_to_xyz` computes it."""

from __future__ import annotations

import numba as nb
import numpy as np

COMBINE = {"spacing": 0, "variance": 1, "either": 2, "both": 3}
_DBL_MAX = np.finfo(np.float64).max


@nb.njit(cache=True, inline="always")
def _partner(v, u, axis, cols):
    """Second pixel of the pair starting at ``(v, u)`` (the pan pair of the last column wraps)."""
    if axis == 0:
        return v + 1, u
    return v, (u + 1 if u + 1 < cols else 0)


@nb.njit(cache=True, inline="always")
def _ray_point(rng, trig, v, u):
    """Sensor-frame point of pixel ``(v, u)`` from its range (NaN without a return)."""
    r = np.float64(rng[v, u])
    h = r * trig[2][v]
    return h * trig[0][u], h * trig[1][u], r * trig[3][v]


@nb.njit(cache=True, inline="always")
def _point(xyz, rng, trig, v, u):
    """Levelled point of pixel ``(v, u)`` as float64 (module docstring; NaN without a return)."""
    if xyz.shape[0] == 0 or not np.isfinite(rng[v, u]):
        return _ray_point(rng, trig, v, u)
    return np.float64(xyz[v, u, 0]), np.float64(xyz[v, u, 1]), np.float64(xyz[v, u, 2])


@nb.njit(cache=True)
def pair_tests(
    rng, trig, axis, n_pairs, thr, thr_col, variance_m, combine, hit, near, far, var_hit
):
    """Tests of the first ``n_pairs`` (rows or columns) pairs along ``axis`` (men_spec 3.1).

    Returns ``Delta_s / r_near`` and ``|Delta r|`` (NaN where a member has no return; sensor-
    frame points) and the flag of the ``combine`` rule (:data:`COMBINE`) of the spacing test
    ``ratio >= thr[v, thr_col[u]]`` and the variance test ``jump > variance_m``. ORs into the
    pixel masks: ``hit`` both members of a flagged pair, ``near`` / ``far`` its nearer / farther
    member (the first one on a tie), ``var_hit`` both members of a pair failing the variance
    test."""
    rows, cols = rng.shape
    shape = (n_pairs, cols) if axis == 0 else (rows, n_pairs)
    ratio = np.empty(shape)
    jump = np.empty(shape)
    flag = np.zeros(shape, dtype=np.bool_)
    for v in range(shape[0]):
        for u in range(shape[1]):
            v1, u1 = _partner(v, u, axis, cols)
            r0 = np.float64(rng[v, u])  # NaN (no return) propagates to both results
            r1 = np.float64(rng[v1, u1])
            x0, y0, z0 = _ray_point(rng, trig, v, u)
            x1, y1, z1 = _ray_point(rng, trig, v1, u1)
            dx, dy, dz = x1 - x0, y1 - y0, z1 - z0
            q = np.sqrt((dx * dx + dy * dy) + dz * dz) / (r0 if r0 <= r1 else r1)
            j = abs(r1 - r0)
            ratio[v, u] = q
            jump[v, u] = j
            spacing = q >= thr[v, thr_col[u]]  # False for NaN
            variance = j > variance_m
            if variance:
                var_hit[v, u] = True
                var_hit[v1, u1] = True
            if combine == 0:
                f = spacing
            elif combine == 1:
                f = variance
            elif combine == 2:
                f = spacing or variance
            else:
                f = spacing and variance
            if f:
                flag[v, u] = True
                hit[v, u] = True
                hit[v1, u1] = True
                if r0 <= r1:
                    near[v, u] = True
                    far[v1, u1] = True
                else:
                    far[v, u] = True
                    near[v1, u1] = True
    return ratio, jump, flag


@nb.njit(cache=True, inline="always")
def _nan_to_num(x):
    """``np.nan_to_num`` of one float64."""
    if np.isnan(x):
        return 0.0
    if np.isinf(x):
        return _DBL_MAX if x > 0 else -_DBL_MAX
    return x


@nb.njit(cache=True)
def boundary_columns(v, u, xyz, rng, trig, tilt_ratio, pan_ratio, tilt_pair, pan_pair, wrap):
    """Per listed pixel: its levelled point (float32), the largest ``nan_to_num`` ratio of the
    tilt and pan pairs it belongs to (at least 0, float32) and whether its pairs with the next
    row / column are flagged."""
    n = v.size
    cols = rng.shape[1]
    pts = np.empty((n, 3), np.float32)
    ratio = np.empty(n, np.float32)
    tilt_next = np.zeros(n, np.bool_)
    pan_next = np.zeros(n, np.bool_)
    for i in range(n):
        a, b = v[i], u[i]
        x, y, z = _point(xyz, rng, trig, a, b)
        pts[i, 0], pts[i, 1], pts[i, 2] = x, y, z
        tilt_next[i] = a < tilt_pair.shape[0] and tilt_pair[a, b]
        pan_next[i] = b < pan_pair.shape[1] and pan_pair[a, b]
        best = 0.0
        if a < tilt_ratio.shape[0]:
            best = max(best, _nan_to_num(tilt_ratio[a, b]))
        if a >= 1:
            best = max(best, _nan_to_num(tilt_ratio[a - 1, b]))
        if b < pan_ratio.shape[1]:
            best = max(best, _nan_to_num(pan_ratio[a, b]))
        if b >= 1 or wrap:
            best = max(best, _nan_to_num(pan_ratio[a, (b if b >= 1 else cols) - 1]))
        ratio[i] = best
    return pts, ratio, tilt_next, pan_next


@nb.njit(cache=True, inline="always")
def _put(x, y, z, fill, n, voxel_m, lo, hi, span, keys):
    """One point: widen the coordinate bounds ``lo`` / ``hi`` (first pass, ``keys`` empty; the
    voxel bounds follow, ``floor(x / voxel_m)`` being monotonic) or write its key: the linear
    index of voxel ``floor(p / voxel_m)`` from ``lo`` (now voxel bounds) times 2, plus 1 for a
    gap-fill sample."""
    if keys.size == 0:
        lo[0], lo[1], lo[2] = min(lo[0], x), min(lo[1], y), min(lo[2], z)
        hi[0], hi[1], hi[2] = max(hi[0], x), max(hi[1], y), max(hi[2], z)
        return n + 1
    ix = np.int64(np.floor(x / voxel_m)) - lo[0]
    iy = np.int64(np.floor(y / voxel_m)) - lo[1]
    iz = np.int64(np.floor(z / voxel_m)) - lo[2]
    keys[n] = ((ix * span[1] + iy) * span[2] + iz) * 2 + fill
    return n + 1


@nb.njit(cache=True)
def surface_walk(
    xyz, rng, trig, flagged, axis, n_pairs, step_m, max_fill_m, voxel_m, lo, hi, span, keys, n
):
    """Returns (``axis`` < 0) or gap-fill samples of the unflagged pairs of returns along ``axis``
    not longer than ``max_fill_m``: interior points every <= ``step_m`` (``k = ceil(length /
    step_m) - 1`` at ``j / (k + 1)``), passed to :func:`_put`; returns the running count ``n``."""
    rows, cols = rng.shape
    if axis < 0:
        for v in range(rows):
            for u in range(cols):
                if np.isfinite(rng[v, u]):
                    x, y, z = _point(xyz, rng, trig, v, u)
                    n = _put(x, y, z, 0, n, voxel_m, lo, hi, span, keys)
        return n
    for v in range(n_pairs if axis == 0 else rows):
        for u in range(cols if axis == 0 else n_pairs):
            v1, u1 = _partner(v, u, axis, cols)
            if flagged[v, u] or not (np.isfinite(rng[v, u]) and np.isfinite(rng[v1, u1])):
                continue
            x0, y0, z0 = _point(xyz, rng, trig, v, u)
            x1, y1, z1 = _point(xyz, rng, trig, v1, u1)
            dx, dy, dz = x1 - x0, y1 - y0, z1 - z0
            length = np.sqrt((dx * dx + dy * dy) + dz * dz)
            if not (length > step_m and length <= max_fill_m):
                continue
            k = max(np.int64(np.ceil(length / step_m)) - 1, 0)
            for j in range(1, k + 1):
                t = j / (k + 1)
                n = _put(x0 + t * dx, y0 + t * dy, z0 + t * dz, 1, n, voxel_m, lo, hi, span, keys)
    return n


@nb.njit(cache=True)
def voxel_counts(sorted_keys):
    """Distinct voxels of sorted :func:`_put` keys with their return and gap-fill counts."""
    n = sorted_keys.size
    uniq = np.empty(n, np.int64)
    n_points = np.zeros(n, np.int32)
    n_filled = np.zeros(n, np.int32)
    m = 0
    prev = -1
    for i in range(n):
        key = sorted_keys[i] >> 1
        if key != prev:
            uniq[m] = key
            m += 1
            prev = key
        if sorted_keys[i] & 1:
            n_filled[m - 1] += 1
        else:
            n_points[m - 1] += 1
    return uniq[:m], n_points[:m], n_filled[:m]
