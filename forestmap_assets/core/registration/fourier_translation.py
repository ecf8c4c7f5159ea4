"""Translation of the Fourier coarse registration (men spec 4.4, corrected Eq. 4.8): corr[t] =
IFFT(FFT[Og_m] conj(FFT[Og_d]))[t] over occupancy grids of the common bounding box, each axis
zero-padded to at least twice its length; ground points weighted by ground_weight (spec 10,
inferred)."""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft


def occupancy_grid(
    points: np.ndarray, origin: np.ndarray, cell_m: float, shape, weights=None
) -> np.ndarray:
    """Occupancy grid (float32): 1 (or the largest point weight) in every cell holding a point
    (spec 4.4, ``Og(x, y, z) = 1`` if at least one point is in the voxel)."""
    idx = np.floor((np.asarray(points, dtype=np.float64) - origin) / cell_m).astype(np.int64)
    ok = np.all((idx >= 0) & (idx < np.asarray(shape)), axis=1)
    g = np.zeros(tuple(int(s) for s in shape), dtype=np.float32)
    w = (
        np.ones(int(ok.sum()), dtype=np.float32)
        if weights is None
        else np.asarray(weights, np.float32)[ok]
    )
    np.maximum.at(g, tuple(idx[ok].T), w)
    return g


def translation_by_correlation(
    model_points: np.ndarray,
    data_points: np.ndarray,
    cell_m: float = 0.2,
    *,
    model_weights=None,
    data_weights=None,
    max_cells: int = 8_000_000,
    bounds=None,
    cache: dict | None = None,
) -> tuple[np.ndarray, float, dict]:
    """Translation ``T`` (3,) moving the (rotated) data onto the model by FFT cross-correlation
    of occupancy grids over the common bounding box (spec 4.4; zero padded, no wrap), the peak
    value and a dict with the grid details. ``T`` is a multiple of the cell (V9). The cell grows
    when the padded grid would exceed ``max_cells`` (inferred memory guard). ``bounds`` = (lo,
    hi) fixes the grid box (it must hold both clouds); with it the model grid's transform is kept
    in ``cache`` and reused by later calls (several data rotations against one model)."""
    m = np.asarray(model_points, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(data_points, dtype=np.float64).reshape(-1, 3)
    if bounds is None:
        lo = np.minimum(m.min(axis=0), d.min(axis=0))
        hi = np.maximum(m.max(axis=0), d.max(axis=0))
    else:
        lo, hi = (np.asarray(b, dtype=np.float64) for b in bounds)
    cell = float(cell_m)
    while True:
        shape = np.floor((hi - lo) / cell).astype(np.int64) + 1
        padded = np.array([sfft.next_fast_len(int(2 * s), real=True) for s in shape])
        if np.prod(padded) <= max_cells:
            break
        cell *= 1.25
    key = (cell, tuple(shape), tuple(lo))
    if bounds is not None and cache is not None and key in cache:
        fm = cache[key]
    else:
        fm = sfft.rfftn(
            occupancy_grid(m, lo, cell, shape, model_weights), s=tuple(padded), workers=-1
        )
        if bounds is not None and cache is not None:
            cache[key] = fm
    fd = sfft.rfftn(occupancy_grid(d, lo, cell, shape, data_weights), s=tuple(padded), workers=-1)
    corr = sfft.irfftn(fm * np.conj(fd), s=tuple(padded), workers=-1)
    best = int(np.argmax(corr))
    k = np.array(np.unravel_index(best, corr.shape))
    t = np.where(k > padded // 2, k - padded, k)  # signed shift
    return (
        t * cell,
        float(corr.flat[best]),
        {
            "cell_m": cell,
            "shape": tuple(int(v) for v in shape),
            "padded": tuple(int(v) for v in padded),
        },
    )
