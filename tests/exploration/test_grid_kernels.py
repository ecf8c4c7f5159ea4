"""The compiled grid update and ray walk (core/exploration/_grid_kernels.py) against the numpy
they replaced (kept here as the reference): the same histograms and the same visible cells."""

from __future__ import annotations

import numpy as np
import pandas as pd

from forestmap_assets.core.exploration.grid import ExplorationGrid
from forestmap_assets.core.exploration.surface import SURFACE_COLUMNS, surface_points
from forestmap_assets.core.exploration.visibility import _ray_circle_t, visible_cells
from forestmap_assets.core.geometry import transform_points


def _grid(ground: bool) -> ExplorationGrid:
    g = ExplorationGrid.from_bounds((-8.0, 8.0, -6.0, 6.0), 0.25, (-0.5, 3.0), dz=0.1)
    if ground:
        xs, ys = g.centres()
        g.ground_z = 0.05 * xs[:, None] - 0.1 * ys[None, :] - 1.2
    return g


def _numpy_add(g: ExplorationGrid, pts, w, m) -> None:
    """The numpy update of men_spec 3.5 as it was before the kernel."""
    ix, iy, h, inside = g.heights(pts[:, 0], pts[:, 1], pts[:, 2])
    cell = ix * g.ny + iy
    iz, ok = g._levels(h, inside)
    idx = cell[ok] * g.nz + iz[ok]
    g.counts += np.bincount(idx, weights=w[ok], minlength=g.counts.size)
    g.measured += np.bincount(idx, weights=m[ok], minlength=g.counts.size)
    top = inside & (h >= g.z_min + g.nz * g.dz)
    g.above += np.bincount(cell[top], weights=w[top], minlength=g.nx * g.ny).reshape(g.shape)
    g.points += np.bincount(cell[inside], weights=m[inside], minlength=g.nx * g.ny).reshape(g.shape)


def _same(a: ExplorationGrid, b: ExplorationGrid) -> None:
    for name in ("counts", "measured", "above", "points"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_add_points_matches_the_numpy_update():
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-10, 10, 5000), rng.uniform(-8, 8, 5000), rng.uniform(-3, 4, 5000)])
    pts[:7] = np.nan  # no return
    pts[7:12, 2] = np.nan  # a cell without a height
    w, m = rng.uniform(0.5, 3.0, len(pts)), rng.uniform(0.0, 0.5, len(pts))
    for ground in (False, True):
        a, b = _grid(ground), _grid(ground)
        for _ in range(2):  # sums onto earlier ones as np.bincount's did
            a.add_points(pts, w, measured=m)
            _numpy_add(b, pts, w, m)
        _same(a, b)
        assert a.counts.sum() > 0 and a.above.sum() > 0 and a.points.sum() > a.measured.sum()


def test_add_surface_is_surface_points_then_add_points():
    rng = np.random.default_rng(5)
    n = 20000
    table = pd.DataFrame({
        "ix": rng.integers(-200, 200, n), "iy": rng.integers(-200, 200, n), "iz": rng.integers(-40, 80, n),
        "n_points": rng.integers(0, 9, n), "n_filled": rng.integers(0, 4, n),
    })[SURFACE_COLUMNS].astype({"ix": "int32", "iy": "int32", "iz": "int32"})
    pose = (1.3, -0.7, 0.4, 37.0)
    a, b = _grid(True), _grid(True)
    a.add_surface(table, 0.05, pose, max_range_m=7.0)
    local = (table[["ix", "iy", "iz"]].to_numpy(float) + 0.5) * 0.05
    keep = np.hypot(local[:, 0], local[:, 1]) <= 7.0
    pts = transform_points(local[keep], pose)
    n_pts = table["n_points"].to_numpy(float)[keep]
    _numpy_add(b, pts, n_pts + table["n_filled"].to_numpy(float)[keep], n_pts)
    # the same voxels (a matrix product may round a centre differently in the last bit)
    assert np.abs(a.counts - b.counts).sum() <= 1e-3 * b.counts.sum()
    assert a.counts.sum() == b.counts.sum() and a.points.sum() == b.points.sum() > 0
    got, n_got, _ = surface_points(table, 0.05, pose, max_range_m=7.0)
    np.testing.assert_allclose(got, pts, atol=1e-12)
    np.testing.assert_array_equal(n_got, n_pts)


def _numpy_visible(grid, pos, occ, stems, radius_m, blind_radius_m, n_rays) -> np.ndarray:
    """visible_cells as the numpy of the whole (positions, rays, samples) array computed it."""
    theta = np.arange(n_rays) * (2 * np.pi / n_rays)
    u = np.column_stack([np.cos(theta), np.sin(theta)])
    t = np.arange(blind_radius_m, radius_m + 1e-9, 0.5 * grid.cell_m)
    occ = occ.ravel()
    t_stem = _ray_circle_t(pos, u, stems)
    xy = pos[:, None, None, :] + t[None, None, :, None] * u[None, :, None, :]
    ix, iy, inside = grid.cell_of(xy[..., 0], xy[..., 1])
    flat = np.where(inside, ix * grid.ny + iy, 0)
    blocked = inside & occ[flat]
    hidden = np.cumsum(blocked, axis=2) - blocked > 0
    seen = inside & ~hidden & (t[None, None, :] < t_stem[:, :, None])
    out = np.zeros((len(pos), grid.nx * grid.ny), dtype=bool)
    rows = np.broadcast_to(np.arange(len(pos))[:, None, None], seen.shape)
    out[rows[seen], flat[seen]] = True
    return out


def test_walked_rays_see_what_the_numpy_rays_saw():
    rng = np.random.default_rng(11)
    g = _grid(False)
    occ = rng.random(g.shape) < 0.03
    stems = np.column_stack([rng.uniform(-8, 8, 25), rng.uniform(-6, 6, 25), rng.uniform(0.05, 0.4, 25)])
    pos = np.column_stack([rng.uniform(-9, 9, 21), rng.uniform(-7, 7, 21)])  # some outside the grid
    got = visible_cells(g, pos, occ, stems, radius_m=9.0, blind_radius_m=1.5, n_rays=360, chunk=8)
    want = _numpy_visible(g, pos, occ, stems, 9.0, 1.5, 360)
    np.testing.assert_array_equal(got, want)
    assert got.sum() > 1000 and not got.all()
