"""Numba kernels of the tree list's slices and silhouettes: :meth:`~forestmap_assets.core.mapping.
stem_slices.StemCells.near`, a range image's points in the stems' marked cells and height bands
in one pass over the image (the numpy form made five passes and three gathers, 30 ms a call on a
rendered scan of 2.3 M points, 18 calls in a tree list; its arithmetic: float64), and
:func:`pixel_ranges`, the range at given pixels of an image stored one row per valid pixel."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True)
def cells_near(x, y, z, lo_x, lo_y, cell, n_x, n_y, z_lo, z_hi, z_min, z_max):
    """Indices (ascending) of the points whose height lies in ``[z_min, z_max]`` and whose cell
    ``(floor((x - lo_x) / cell), floor((y - lo_y) / cell))`` of the ``n_x`` x ``n_y`` grid
    (``z_lo``, ``z_hi`` raveled) holds it within its band."""
    out = np.empty(z.shape[0], np.int64)
    k = 0
    for i in range(z.shape[0]):
        zi = np.float64(z[i])
        if not (zi >= z_min and zi <= z_max):  # NaN is outside, as in numpy
            continue
        fx = (np.float64(x[i]) - lo_x) / cell
        fy = (np.float64(y[i]) - lo_y) / cell
        if not (fx >= 0.0 and fy >= 0.0 and fx < n_x and fy < n_y):
            continue
        c = np.int64(fx) * n_y + np.int64(fy)
        if zi >= z_lo[c] and zi <= z_hi[c]:
            out[k] = i
            k += 1
    return out[:k]


@nb.njit(cache=True)
def row_major(row, col):
    """Whether the pixels are in row-major order (rows ascending, columns ascending in a row), as
    :meth:`~forestmap_assets.core.features.range_image.RangeImage.to_table` writes them."""
    for i in range(1, row.shape[0]):
        if row[i] < row[i - 1] or (row[i] == row[i - 1] and col[i] <= col[i - 1]):
            return False
    return True


@nb.njit(cache=True)
def pixel_ranges(row, col, rng, rows, cols):
    """``out[e, j]``: the range at pixel ``(rows[e], cols[e, j])`` of an image given as its valid
    pixels in row-major order (``row, col, rng``), ``inf`` where the pixel holds none: a binary
    search for the row, then for the column within it."""
    out = np.full(cols.shape, np.inf, np.float32)
    for e in range(rows.shape[0]):
        start = np.searchsorted(row, rows[e])
        line = col[start:np.searchsorted(row, rows[e], side="right")]
        for j in range(cols.shape[1]):
            k = np.searchsorted(line, cols[e, j])
            if k < line.shape[0] and line[k] == cols[e, j]:
                out[e, j] = rng[start + k]
    return out
