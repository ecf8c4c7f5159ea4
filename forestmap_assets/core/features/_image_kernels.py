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
