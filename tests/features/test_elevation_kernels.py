"""The numba elevation kernels (issue 18) against the sort-based numpy formulation they replaced:
same cells, z (first of equal values, so the sign of a zero too), counts, dtypes and order, on
both the dense and the hashed path."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

import forestmap_assets.core.features.elevation as elevation
from forestmap_assets.core.features.elevation import elevation_grid
from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.params import ElevationParams


def _sorted_reference(pts: np.ndarray, cell_m: float, mode: str, max_distance_m) -> pd.DataFrame:
    """The former lexsort + unique implementation (finite rows only)."""
    pts = pts[np.isfinite(pts).all(axis=1)]
    if max_distance_m is not None:
        pts = pts[(np.abs(pts[:, 0]) < max_distance_m) & (np.abs(pts[:, 1]) < max_distance_m)]
    if pts.shape[0] == 0:
        dtypes = {"ix": "int64", "iy": "int64", "z": "float64", "n": "int64"}
        return pd.DataFrame({c: pd.Series(dtype=t) for c, t in dtypes.items()})
    ij = np.floor(pts[:, :2] / cell_m).astype(np.int64)
    lo = ij.min(axis=0)
    span = ij.max(axis=0) - lo + 1
    keys = (ij[:, 1] - lo[1]) * span[0] + (ij[:, 0] - lo[0])
    z = pts[:, 2]
    order = np.lexsort((z if mode == "lowest" else -z, keys))
    uniq, first, counts = np.unique(keys[order], return_index=True, return_counts=True)
    ix, iy = uniq % span[0] + lo[0], uniq // span[0] + lo[1]
    return pd.DataFrame({"ix": ix, "iy": iy, "z": z[order][first], "n": counts})


def _points(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    k = rng.integers(-40, 40, (20000, 2))
    p = np.c_[k * 0.1, np.round(rng.normal(0.0, 1.0, 20000), 1)]  # cell edges, many ties
    p[::3, :2] += rng.uniform(0.0, 0.1, (p[::3].shape[0], 2))
    p[::11, :2] = np.nextafter(k[::11] * 0.1, -np.inf)
    p[::13, 2] = -0.0
    p[::29] = np.nan
    p[::31, 1] = np.inf
    p[::37, 0] = rng.normal(0.0, 30.0, p[::37].shape[0])
    return p


@pytest.mark.parametrize("path", ["auto", "dense", "hashed"])
@pytest.mark.parametrize("mode", ["lowest", "highest"])
@pytest.mark.parametrize("max_distance_m", [None, 3.0])
def test_kernels_match_sorted_formulation(monkeypatch, path, mode, max_distance_m):
    if path == "dense":
        monkeypatch.setattr(elevation, "DENSE_MAX_CELLS", 10**9)
        monkeypatch.setattr(elevation, "DENSE_CELLS_PER_POINT", 10**9)
    elif path == "hashed":
        monkeypatch.setattr(elevation, "DENSE_MAX_CELLS", 0)
    params = ElevationParams(cell_m=0.1, mode=mode)
    for seed in range(2):
        pts = _points(seed)
        got = elevation_grid(pts, params, max_distance_m=max_distance_m)
        want = _sorted_reference(pts, 0.1, mode, max_distance_m)
        pd.testing.assert_frame_equal(got, want, check_exact=True)
        assert np.array_equal(np.signbit(got["z"].to_numpy()), np.signbit(want["z"].to_numpy()))
        table = pd.DataFrame(pts[np.isfinite(pts).all(axis=1)], columns=list("xyz"))
        from_table = elevation_grid(table, params, max_distance_m=max_distance_m)
        pd.testing.assert_frame_equal(from_table, want, check_exact=True)


def test_far_points_use_the_hash_and_empty_inputs():
    params = ElevationParams()
    pts = np.array([[1e5, -2e5, 1.0], [0.05, 0.05, 2.0], [0.06, 0.01, 1.5], [-3e5, 4e5, 0.0]])
    got = elevation_grid(pts, params)
    pd.testing.assert_frame_equal(got, _sorted_reference(pts, 0.1, "lowest", None), check_exact=True)
    assert got["iy"].tolist() == [-2000000, 0, 4000000] and got["n"].tolist() == [1, 2, 1]
    empties = (np.zeros((0, 3)), np.full((2, 3), np.nan), pd.DataFrame(columns=list("xyz"), dtype=float))
    for empty in empties:
        out = elevation_grid(empty, params)
        assert len(out) == 0 and list(out.dtypes.astype(str)) == ["int64", "int64", "float64", "int64"]
    img = RangeImage(np.full((3, 4), np.nan, np.float32), np.arange(4.0), np.arange(3.0)[::-1])
    assert len(elevation_grid(img, params, max_distance_m=10.0)) == 0


def test_range_image_matches_its_valid_points():
    rng = np.random.default_rng(4)
    r = rng.uniform(1.0, 20.0, (40, 90)).astype(np.float32)
    r[rng.random(r.shape) < 0.2] = np.nan
    az, el = np.linspace(-180, 180, 90, endpoint=False), np.linspace(30, -30, 40)
    img = RangeImage(r, az, el, (1.5, -2.0))
    for mode in ("lowest", "highest"):
        want = _sorted_reference(img.xyz[img.valid], 0.1, mode, 12.0)
        got = elevation_grid(img, ElevationParams(mode=mode), max_distance_m=12.0)
        pd.testing.assert_frame_equal(got, want, check_exact=True)
