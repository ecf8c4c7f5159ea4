"""Ground elevation maps (spec 9): lowest-hit grids, merging with poses, rendering grid, files."""

from __future__ import annotations

import os

import numpy as np
import pandas as pd
import pytest

from forestmap_assets.core.features.elevation import (
    ElevationGrid,
    elevation_grid,
    merge_elevation,
    render_grid,
)
from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.outputs.elevation_files import (
    elevation_png,
    load_elevation_npz,
    save_elevation_npz,
)
from forestmap_assets.params import ElevationParams

A, B, C = 0.04, -0.03, -1.3  # global ground z = A x + B y + C


def _ground_scan(pose, rows=120, cols=720, noise=0.01, seed=0, max_range=25.0) -> RangeImage:
    """Range image of the global ground plane seen from ``pose`` = (x, y, z, heading_deg),
    exact ray casting in the scan's levelled frame (p_global = R_z(heading) p + t)."""
    px, py, pz, heading = pose
    az = np.linspace(-180.0, 180.0, cols, endpoint=False)
    el = np.linspace(38.7, -38.7, rows)
    a, e = np.radians(az)[None, :], np.radians(el)[:, None]
    d = np.stack(np.broadcast_arrays(np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)), -1)
    c, s = np.cos(np.radians(heading)), np.sin(np.radians(heading))
    dg = np.stack([c * d[..., 0] - s * d[..., 1], s * d[..., 0] + c * d[..., 1], d[..., 2]], -1)
    # Ray p = o + r dg meets z = A x + B y + C.
    denom = dg[..., 2] - A * dg[..., 0] - B * dg[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        r = (A * px + B * py + C - pz) / denom
    r = np.where((denom < 0) & (r > 0) & (r < max_range), r, np.nan)
    r = r + np.random.default_rng(seed).normal(0.0, noise, r.shape)
    return RangeImage(r.astype(np.float32), az, el)


def _fit_plane(table: pd.DataFrame, cell: float) -> np.ndarray:
    x = (table["ix"].to_numpy() + 0.5) * cell
    y = (table["iy"].to_numpy() + 0.5) * cell
    M = np.c_[x, y, np.ones_like(x)]
    return np.linalg.lstsq(M, table["z"].to_numpy(), rcond=None)[0]


def test_ground_plane_recovered_from_synthetic_scan():
    noise = 0.01
    params = ElevationParams()
    table = elevation_grid(_ground_scan((0.0, 0.0, 0.0, 0.0), noise=noise), params)
    assert list(table.columns) == ["ix", "iy", "z", "n"] and len(table) > 1000
    assert table["n"].min() >= 1 and table[["ix", "iy"]].duplicated().sum() == 0
    a, b, c = _fit_plane(table, params.cell_m)
    # Lowest hit per cell: biased low by a few noise sigmas and by the slope inside a cell.
    slope_bias = 0.5 * params.cell_m * (abs(A) + abs(B))
    assert C - 3 * noise - slope_bias < c < C + noise
    assert abs(a - A) < 0.005 and abs(b - B) < 0.005
    # Highest mode sits above the lowest one in every cell.
    high = elevation_grid(
        _ground_scan((0.0, 0.0, 0.0, 0.0), noise=noise), ElevationParams(mode="highest")
    )
    both = table.merge(high, on=["ix", "iy"], suffixes=("_lo", "_hi"))
    assert len(both) == len(table) and (both["z_hi"] >= both["z_lo"]).all()


def test_lowest_hit_semantics_and_cell_boundaries():
    params = ElevationParams(cell_m=0.1)
    pts = np.array([[0.05, 0.05, 0.5], [0.06, 0.04, 0.9], [0.01, 0.09, 0.7], [-0.01, 0.05, 3.0]])
    t = elevation_grid(pts, params).set_index(["ix", "iy"])
    assert t.loc[(0, 0), "z"] == 0.5 and t.loc[(0, 0), "n"] == 3
    assert t.loc[(-1, 0), "z"] == 3.0  # x = -0.01 lies in cell [-0.1, 0)
    # A point above the lowest one in the same cell does not change it; a lower one does.
    above = elevation_grid(np.vstack([pts, [[0.02, 0.02, 0.6]]]), params)
    assert above.set_index(["ix", "iy"]).loc[(0, 0), "z"] == 0.5
    below = elevation_grid(np.vstack([pts, [[0.02, 0.02, 0.1]]]), params)
    assert below.set_index(["ix", "iy"]).loc[(0, 0), "z"] == 0.1
    high = elevation_grid(pts, ElevationParams(cell_m=0.1, mode="highest"))
    assert high.set_index(["ix", "iy"]).loc[(0, 0), "z"] == 0.9
    # Same input as a DataFrame and NaN rows ignored; distance limit drops far points.
    df = pd.DataFrame(np.vstack([pts, [[np.nan] * 3]]), columns=["x", "y", "z"])
    assert len(elevation_grid(df.dropna(), params)) == 2
    assert len(elevation_grid(np.vstack([pts, [[np.nan] * 3]]), params)) == 2
    assert len(elevation_grid(np.array([[50.0, 0.0, 1.0]]), params, max_distance_m=30.0)) == 0


def test_merging_two_scans_of_the_same_ground_agrees_in_the_overlap():
    cell = 0.1
    params = ElevationParams(cell_m=cell)
    poses = [(0.0, 0.0, 0.3, 0.0), (6.0, 2.0, 0.5, 37.0)]
    tables = [elevation_grid(_ground_scan(p, seed=i), params) for i, p in enumerate(poses)]
    one = merge_elevation([(tables[0], poses[0])], cell, "lowest")
    two = merge_elevation([(tables[1], poses[1])], cell, "lowest")
    both = merge_elevation(list(zip(tables, poses, strict=True)), cell, "lowest")

    def on(grid, ref):  # resample ``grid`` onto the cells of ``ref`` (same cell size)
        out = np.full(ref.z.shape, np.nan)
        ox, oy = round((grid.x0 - ref.x0) / cell), round((grid.y0 - ref.y0) / cell)
        ny, nx = grid.z.shape
        out[oy : oy + ny, ox : ox + nx] = grid.z
        return out

    z1, z2 = on(one, both), on(two, both)
    overlap = np.isfinite(z1) & np.isfinite(z2)
    assert overlap.sum() > 2000
    diff = z1[overlap] - z2[overlap]
    assert np.median(np.abs(diff)) < 0.02 and np.percentile(np.abs(diff), 95) < 0.05
    np.testing.assert_array_equal(both.z[overlap], np.minimum(z1, z2)[overlap])
    # The merged grid is the global ground plane (at cell centres).
    xc, yc = both.centres()
    truth = A * xc[None, :] + B * yc[:, None] + C
    ok = np.isfinite(both.z)
    assert np.percentile(np.abs(both.z[ok] - truth[ok]), 95) < 0.05
    # A wrong pose (z off by 0.2 m) makes the overlap disagree: the check can fail.
    bad = merge_elevation([(tables[1], (6.0, 2.0, 0.7, 37.0))], cell, "lowest")
    zb = on(bad, both)
    ob = overlap & np.isfinite(zb)
    assert np.median(np.abs(z1[ob] - zb[ob])) > 0.15


def test_rotated_merge_is_seamless():
    """A dense disk of cells rotated by 37 deg and re-binned at the same cell size leaves no
    holes (spec 13.21 'seamless overlap'); plain centre transfer (supersample=1) would."""
    cell = 0.1
    i, j = np.meshgrid(np.arange(-60, 60), np.arange(-60, 60))
    disk = np.hypot(i + 0.5, j + 0.5) < 55
    t = pd.DataFrame({"ix": i[disk], "iy": j[disk], "z": 0.01 * i[disk], "n": 1})
    pose = (1.23, -0.4, 0.0, 37.0)
    g = merge_elevation([(t, pose)], cell, "lowest")
    xc, yc = g.centres()
    inside = np.hypot(xc[None, :] - pose[0], yc[:, None] - pose[1]) < 5.0
    assert np.isnan(g.z[inside]).mean() == 0.0
    plain = merge_elevation([(t, pose)], cell, "lowest", supersample=1)
    xp, yp = plain.centres()
    assert np.isnan(plain.z[np.hypot(xp[None, :] - pose[0], yp[:, None] - pose[1]) < 5.0]).any()


def test_merge_transforms_cell_centres_with_the_pose():
    t = pd.DataFrame({"ix": [10], "iy": [0], "z": [1.0], "n": [1]})  # centre (1.05, 0.05)
    g = merge_elevation([(t, (2.0, 3.0, 0.5, 90.0))], 0.1, "lowest", supersample=1)
    iy, ix = np.nonzero(np.isfinite(g.z))
    x = g.x0 + (ix + 0.5) * g.cell_m
    y = g.y0 + (iy + 0.5) * g.cell_m
    # R_z(90) (1.05, 0.05) + (2, 3) = (1.95, 4.05)
    assert np.allclose([x[0], y[0]], [1.95, 4.05], atol=0.051) and g.z[iy[0], ix[0]] == 1.5
    assert merge_elevation([], 0.1).z.size == 0


def test_render_grid_is_mean_of_five_lowest_fine_cells():
    rng = np.random.default_rng(7)
    z = np.full((12, 18), np.nan)  # 1.2 m x 1.8 m at 0.1 m -> 2 x 3 coarse 0.6 m cells
    block = rng.permutation(36).astype(float).reshape(6, 6)
    z[0:6, 0:6] = block  # full block: mean of 0..4
    z[0:6, 6:12][[0, 2, 5], [1, 3, 4]] = [7.0, 3.0, 5.0]  # three values only
    z[6:12, 12:18] = 2.0
    z[8, 14] = -1.0
    grid = ElevationGrid(z, x0=-0.3, y0=1.2, cell_m=0.1)
    r = render_grid(grid, cell_m=0.6, n_lowest=5)
    assert r.z.shape == (2, 3) and (r.x0, r.y0, r.cell_m) == (-0.3, 1.2, 0.6)
    assert r.z[0, 0] == pytest.approx(2.0)  # (0 + 1 + 2 + 3 + 4) / 5
    assert r.z[0, 1] == pytest.approx(5.0)  # only three cells have values
    assert r.z[1, 2] == pytest.approx((4 * 2.0 - 1.0) / 5)
    assert np.isnan(r.z[0, 2]) and np.isnan(r.z[1, 0])


def test_npz_round_trip(tmp_path):
    z = np.arange(12, dtype=float).reshape(3, 4)
    z[1, 2] = np.nan
    grid = ElevationGrid(z, x0=-3.2, y0=4.5, cell_m=0.1, mode="highest")
    path = save_elevation_npz(tmp_path / "sub" / "elevation.npz", grid)
    assert path.exists() and os.listdir(path.parent) == ["elevation.npz"]
    with np.load(path) as f:
        assert set(f.files) == {"z", "x0", "y0", "cell_m", "mode"}
    back = load_elevation_npz(path)
    np.testing.assert_array_equal(back.z, z)
    assert (back.x0, back.y0, back.cell_m, back.mode) == (-3.2, 4.5, 0.1, "highest")


def test_png_written_atomically(tmp_path):
    scan = _ground_scan((0.0, 0.0, 0.0, 0.0), rows=60, cols=360)
    table = elevation_grid(scan, ElevationParams())
    grid = merge_elevation([(table, (0.0, 0.0, 0.0, 0.0))], 0.1)
    scans = pd.DataFrame({"scan": ["T", "S"], "x": [0.0, 3.0], "y": [0.0, 1.0]})
    trees = np.array([[2.0, 2.0], [-1.0, 4.0]])
    out = elevation_png(tmp_path / "elevation.png", grid, "T", scan_positions=scans, trees=trees)
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    assert os.listdir(tmp_path) == ["elevation.png"]
    # Overwriting keeps a single file; an empty grid still gives a picture.
    elevation_png(out, merge_elevation([], 0.1), "empty")
    assert os.listdir(tmp_path) == ["elevation.png"] and out.read_bytes()[:4] == b"\x89PNG"
