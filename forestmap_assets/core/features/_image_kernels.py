"""Numba kernel of :meth:`~forestmap_assets.core.features.range_image.RangeImage.from_table`:
the stored pixels' levelled points turned back into the scanner frame and placed in the
organised image in one pass (the arithmetic of ``lev @ R`` in float64, then float32)."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True)
def scatter_points(flat, x, y, z, rot, out):
    """``out[flat[k]] = (x, y, z)[k] @ rot`` for every stored pixel ``k``; ``out`` is the
    (rows * cols, 3) float32 image, NaN elsewhere."""
    for k in range(flat.shape[0]):
        p = flat[k]
        a, b, c = np.float64(x[k]), np.float64(y[k]), np.float64(z[k])
        for j in range(3):
            out[p, j] = np.float32(a * rot[0, j] + b * rot[1, j] + c * rot[2, j])


@nb.njit(cache=True)
def gather_points(range_m, points):
    """The valid pixels (finite range) of an image in row-major order: row, col (int32), range
    and the float32 points (rows, cols, 3) there, in one pass (:meth:`RangeImage.to_table`)."""
    rows, cols = range_m.shape
    n = 0
    for i in range(rows):
        for j in range(cols):
            if np.isfinite(range_m[i, j]):
                n += 1
    v = np.empty(n, np.int32)
    u = np.empty(n, np.int32)
    r = np.empty(n, np.float32)
    x = np.empty(n, np.float32)
    y = np.empty(n, np.float32)
    z = np.empty(n, np.float32)
    k = 0
    for i in range(rows):
        for j in range(cols):
            if np.isfinite(range_m[i, j]):
                v[k], u[k], r[k] = i, j, range_m[i, j]
                x[k], y[k], z[k] = points[i, j, 0], points[i, j, 1], points[i, j, 2]
                k += 1
    return v, u, r, x, y, z
