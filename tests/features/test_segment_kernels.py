"""Numba kernels of the scan-line segmentation (spec 2.2-2.4) against the plain numpy / brute-force
formulations they replaced: the results must be the same bit for bit."""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from forestmap_assets.core.features import _segment_kernels as K
from forestmap_assets.core.features.segments import (
    blocking_max_filter,
    link_chains,
    occluder_window,
)


def _numpy_window(range_m, elevation_deg, daz, occ, max_window_px):
    pitch = np.asarray(range_m, np.float64) * np.cos(np.radians(elevation_deg))[:, None]
    pitch *= daz
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        x = np.ceil(occ / pitch + 1.0)
    x = np.clip(np.where(np.isfinite(x), x, 1.0), 1, max_window_px)
    w = x.astype(np.int64)
    return w + (w % 2 == 0)


def test_occluder_window_matches_the_numpy_formula():
    rng = np.random.default_rng(9)
    r = rng.uniform(0.01, 80, (30, 200)).astype(np.float32)
    r[rng.random(r.shape) < 0.1] = np.nan
    r[0, :5] = [0.0, -1.0, np.inf, -np.inf, 1e-30]
    el = np.linspace(89.9, -89.9, 30)
    el[3], el[4] = 90.0, -95.0
    for daz in (np.radians(0.108), 0.0, 1.3e-3):
        for occ in (0.04, 0.0):
            for mw in (101, 1, 2, 1001):
                with np.errstate(invalid="ignore"):
                    want = _numpy_window(r, el, daz, occ, mw)
                got = occluder_window(r, el, daz, occ, mw)
                assert got.dtype == np.int64
                np.testing.assert_array_equal(got, want)
    # float64 ranges, a column, a single row broadcast over the rows, lists
    for rr, ee in [(r.astype(np.float64) * 1.0000001, el), (r[:, 7:8], el), (r[0], el),
                   ([[10.0, 2.0, 0.5, np.nan]], [0.0])]:
        with np.errstate(invalid="ignore"):
            want = _numpy_window(rr, ee, 0.0018, 0.04, 101)
        np.testing.assert_array_equal(occluder_window(rr, ee, 0.0018, 0.04, 101), want)


def test_blocking_max_filter_edge_cases_equal_brute_force():
    rng = np.random.default_rng(7)
    for rows, cols in [(1, 1), (1, 7), (6, 60), (3, 2), (0, 5), (5, 0)]:
        r = rng.uniform(0.5, 60, (rows, cols)).astype(np.float32)
        r[rng.random(r.shape) < 0.2] = np.nan
        if rows > 2:
            r[2] = np.nan  # an all-NaN row
        for w in (np.ones((rows, cols), np.int64),  # width 1 everywhere
                  rng.integers(1, 260, size=(rows, cols)),  # any width, even ones too
                  np.full((rows, cols), 2 * cols + 1),  # wider than the row
                  rng.choice([1, 3, 129], size=(rows, cols)).astype(np.int32)):
            want = np.full(r.shape, np.nan, np.float32)
            for i in range(rows):
                for j in range(cols):
                    if np.isfinite(r[i, j]):
                        h = (w[i, j] - 1) // 2
                        want[i, j] = np.nanmax(r[i, max(j - h, 0):j + h + 1])
            got = blocking_max_filter(r, w)
            assert got.dtype == np.float32 and got.shape == r.shape
            np.testing.assert_array_equal(got, want)


def test_run_split_compares_float32_steps_like_numpy():
    f = np.array([[0.0, np.float32(0.1), 5.0, 5.0 + np.float32(0.25), np.nan, 7.0]], np.float32)
    for step in (0.1, np.float64(0.1), 0.25):
        joined = np.abs(f[0, 1:] - f[0, :-1]) <= step
        starts, ends = K.find_runs(f, K.weak_threshold(f.dtype, step))
        want = np.flatnonzero(np.isfinite(f[0]) & ~np.r_[False, joined])
        np.testing.assert_array_equal(starts, want)
        assert ends.size == starts.size and (ends >= starts).all()


def test_link_chains_matches_all_pairs_components():
    rng = np.random.default_rng(0)
    for _ in range(40):
        n, cols = int(rng.integers(1, 200)), int(rng.integers(5, 300))
        row = rng.integers(0, 12, n)
        c0 = rng.integers(0, cols, n)
        c1 = np.minimum(c0 + rng.integers(0, cols // 3 + 2, n), cols - 1)
        rm = rng.choice(np.round(rng.uniform(1, 3, 40), 2), n) + (rng.random(n) < 0.1) * np.nan
        df = pd.DataFrame({"row": row, "col0": c0, "col1": c1, "r_mid": rm})
        a, b = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        with np.errstate(invalid="ignore"):
            ok = ((row[b] == row[a] + 1) & (c0[b] <= c1[a]) & (c1[b] >= c0[a])
                  & (np.abs(rm[b] - rm[a]) <= 0.11))
        g = coo_matrix((np.ones(ok.sum()), (a[ok], b[ok])), shape=(n, n))
        _, lab = connected_components(g, directed=False)
        first = {}
        want = np.array([first.setdefault(x, len(first)) for x in lab])
        np.testing.assert_array_equal(link_chains(df, cols, 0.11), want)
