"""Numba kernels that turn a point cloud's coordinates into range, azimuth and elevation
(spec 1.2, :func:`forestmap_assets.io.angular_grid.spherical_angles`,
:mod:`forestmap_assets.io.readers_clouds`): LAS integer coordinates to scanner-frame float64
x, y, z (laspy's ``X * scale + offset``, then a project-frame file's ``to_scanner``), their
hypots, and LAS colour to uint8. Each gives numpy's values bit for bit; the arctangents stay
numpy's (its SIMD arctan2 is not libm's, and 20 times faster than a libm loop).

``hypot`` is Borges' corrected hypot (C. F. Borges, "An improved algorithm for hypot(a, b)",
2019, arXiv:1904.09481: ``sqrt(ax^2 + ay^2)`` corrected by one step without FMA), the algorithm
glibc's libm uses from 2.35 on, in plain float64 operations, so the loop vectorises (1 ns a
point instead of libm's 17); the rare arguments that need scaling (huge, tiny, not finite) go
to libm's own. :func:`fast_hypot` checks it against libm's ``hypot`` (which numpy uses) on a few
hundred thousand arguments once per process; where they differ (another libm) libm's is used
throughout."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from forestmap_assets.io._projection_kernels import start_threads

_LARGE, _TINY, _EPS = 2.0**511, 2.0**-459, 2.0**-54  # beyond these, libm scales the arguments
_BLOCK = 1 << 14  # points per parallel task


@nb.njit(cache=True, inline="always", error_model="numpy")
def _hypot_core(x, y):
    """Borges' corrected ``hypot`` of two finite arguments that need no scaling (see
    :func:`_rare`)."""
    a, b = abs(x), abs(y)
    ax = b if a < b else a
    ay = a if a < b else b
    h = math.sqrt(ax * ax + ay * ay)
    d1, d2 = h - ay, h - ax
    up = h <= ay + ay
    t1 = ax * (d1 + d1 - ax) if up else 2.0 * d2 * (ax - 2.0 * ay)
    t2 = (d1 - 2.0 * (ax - ay)) * d1 if up else (4.0 * d2 - ay) * ay + d2 * d2
    return ax + ay if ay <= ax * _EPS else h - (t1 + t2) / (h + h)


@nb.njit(cache=True, inline="always")
def _rare(x, y):
    """Arguments :func:`_hypot_core` does not cover: not finite, beyond ``2^511``, or one
    below ``2^-459`` without being negligible beside the other."""
    a, b = abs(x), abs(y)
    ax = b if a < b else a
    ay = a if a < b else b
    return not ax <= _LARGE or (not ay >= _TINY and not (ax >= _TINY and ay <= ax * _EPS))


@nb.njit(cache=True, error_model="numpy")
def fix_rare(x, y, z, h, r):
    """libm's hypots where :func:`_hypot_core` was not valid."""
    for i in range(x.size):
        if _rare(x[i], y[i]) or _rare(h[i], z[i]):
            h[i] = math.hypot(x[i], y[i])
            r[i] = math.hypot(h[i], z[i])


@nb.njit(cache=True, inline="always", error_model="numpy")
def _block_hypots(x, y, z, h, r, s, e, fast):
    """:func:`hypots` of the points ``s:e`` (one loop a step: they vectorise); returns how
    many are left to libm."""
    if not fast:
        for i in range(s, e):
            h[i] = math.hypot(x[i], y[i])
            r[i] = math.hypot(h[i], z[i])
        return 0
    for i in range(s, e):
        h[i] = _hypot_core(x[i], y[i])
    for i in range(s, e):
        r[i] = _hypot_core(h[i], z[i])
    k = 0
    for i in range(s, e):
        k += _rare(x[i], y[i]) | _rare(h[i], z[i])
    return k


@nb.njit(cache=True, parallel=True, error_model="numpy")
def _hypot_pairs(x, y, z, h, r, fast):
    """``h = hypot(x, y)``, ``r = hypot(h, z)`` (r of any float dtype); returns the number of
    points left to libm (:func:`fix_rare`)."""
    n = x.size
    rare = np.zeros((n + _BLOCK - 1) // _BLOCK, np.int64)
    for b in nb.prange(rare.size):
        rare[b] = _block_hypots(x, y, z, h, r, b * _BLOCK, min(n, (b + 1) * _BLOCK), fast)
    return rare.sum()


def hypots(x, y, z, h, r) -> None:
    """``h = hypot(x, y)`` and ``r = hypot(h, z)`` (numpy's values; ``r`` float32 or float64):
    one parallel pass over the points."""
    fast = fast_hypot()
    if _hypot_pairs(x, y, z, h, r, fast) and fast:
        fix_rare(x, y, z, h, r)


@nb.njit(cache=True, parallel=True, error_model="numpy")
def las_xyz(X, Y, Z, scale, offset, m, moved, x, y, z, h, r, fast):
    """Scanner-frame float64 coordinates of LAS points (``X * scale + offset``, laspy's; then
    ``m`` (4 x 4) applied when ``moved``, as ``x m00 + y m01 + z m02 + m03``) into ``x, y, z``,
    ``h = hypot(x, y)`` and the range ``r = hypot(h, z)`` (float32); returns the number of
    points whose hypots are to be redone by libm (:func:`fix_rare`)."""
    n = X.size
    rare = np.zeros((n + _BLOCK - 1) // _BLOCK, np.int64)
    for b in nb.prange(rare.size):
        s, e = b * _BLOCK, min(n, (b + 1) * _BLOCK)
        for i in range(s, e):
            x[i] = X[i] * scale[0] + offset[0]
            y[i] = Y[i] * scale[1] + offset[1]
            z[i] = Z[i] * scale[2] + offset[2]
        if moved:
            for i in range(s, e):
                px, py, pz = x[i], y[i], z[i]
                x[i] = px * m[0, 0] + py * m[0, 1] + pz * m[0, 2] + m[0, 3]
                y[i] = px * m[1, 0] + py * m[1, 1] + pz * m[1, 2] + m[1, 3]
                z[i] = px * m[2, 0] + py * m[2, 1] + pz * m[2, 2] + m[2, 3]
        rare[b] = _block_hypots(x, y, z, h, r, s, e, fast)
    return rare.sum()


@nb.njit(cache=True, parallel=True, error_model="numpy")
def rgb8(rgb, full_scale, out):
    """``clip(rint(rgb * (255 / full_scale)), 0, 255)`` as uint8 (``readers_common.to_rgb8``
    of non-negative integers)."""
    k = 255.0 / full_scale
    for i in nb.prange(rgb.shape[0]):
        for c in range(3):
            out[i, c] = np.uint8(min(max(np.rint(np.float64(rgb[i, c]) * k), 0.0), 255.0))


@nb.njit(cache=True, error_model="numpy")
def _hypot_differs(x, y):
    n = 0
    for i in range(x.size):
        a = math.hypot(x[i], y[i])
        b = a if _rare(x[i], y[i]) else _hypot_core(x[i], y[i])
        n += not (a == b or (a != a and b != b))
    return n


_FAST: list[bool] = []


def fast_hypot() -> bool:
    """Whether :func:`_hypot_core` gives this process's libm ``hypot`` values: checked once on
    scanner-like coordinates, near-equal and far-apart pairs, and extreme magnitudes."""
    if not _FAST:
        start_threads()
        rng = np.random.default_rng(18)
        n = 50_000
        xs = [rng.integers(-(2**31), 2**31, n) * 1e-4, rng.normal(0.0, 30.0, n),
              np.exp(rng.uniform(-745.0, 709.0, n)), rng.uniform(0.5, 2.0, n)]
        ys = [rng.integers(-(2**31), 2**31, n) * 1e-4, rng.normal(0.0, 30.0, n),
              np.exp(rng.uniform(-745.0, 709.0, n)), xs[3] * rng.uniform(0.5, 2.0, n)]
        xs.append(xs[1])
        ys.append(xs[1] * (1.0 + rng.normal(0.0, 1e-9, n)))
        special = np.array([0.0, -0.0, 1.0, 3.0, 1e-320, 2.0**-459, 2.0**511, 1e308, np.inf,
                            np.nan])
        xs.append(np.repeat(special, special.size))
        ys.append(np.tile(special, special.size))
        _FAST.append(not _hypot_differs(np.concatenate(xs), np.concatenate(ys)))
    return _FAST[0]
