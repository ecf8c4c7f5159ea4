"""Spherical projection of unorganised clouds into range images (spec 1.2)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from scipy.spatial import cKDTree

from forestmap_assets.core.features.range_image import spherical_to_xyz
from forestmap_assets.io.projection import (
    estimate_angular_step,
    fill_ratio,
    nearest_per_pixel,
    neighbour_fill,
    project_to_range_image,
    spherical_angles,
)


def grid_image(rows, cols, az_step, el_step, az0, el0, *, seed=0, dropout=0.1):
    """Ranges on an exact (az, el) grid; NaN dropouts inside, full border rows/columns."""
    rng = np.random.default_rng(seed)
    az = az0 + az_step * np.arange(cols)
    el = el0 - el_step * np.arange(rows)
    r = rng.uniform(2.0, 30.0, (rows, cols)).astype(np.float32)
    r[rng.random((rows, cols)) < dropout] = np.nan
    r[0, :], r[-1, :], r[:, 0], r[:, -1] = 5.0, 6.0, 7.0, 8.0
    return r, az, el


def cloud(r, az, el):
    m = np.isfinite(r)
    return spherical_to_xyz(r, az, el)[m], m


def assert_same_image(img, r, az, el):
    assert img.shape == r.shape
    np.testing.assert_array_equal(np.isnan(img.range_m), np.isnan(r))
    np.testing.assert_allclose(img.range_m[np.isfinite(r)], r[np.isfinite(r)], rtol=1e-6)
    np.testing.assert_allclose(img.azimuth_deg, az, atol=1e-8)
    np.testing.assert_allclose(img.elevation_deg, el, atol=1e-8)


def jittered_cloud(r, az, el, az_step, el_step, *, sigma=0.1, dropout=0.1, seed=1):
    """Per-point angular jitter (sigma in steps) and a random dropout of returns."""
    rng = np.random.default_rng(seed)
    rows, cols = r.shape
    keep = np.isfinite(r) & (rng.random(r.shape) >= dropout)
    a = np.radians(az[None, :] + rng.normal(0, sigma * az_step, (rows, cols)))[keep]
    e = np.radians(el[:, None] + rng.normal(0, sigma * el_step, (rows, cols)))[keep]
    rr = r[keep].astype(np.float64)
    xyz = np.column_stack([rr * np.cos(e) * np.cos(a), rr * np.cos(e) * np.sin(a), rr * np.sin(e)])
    return xyz, keep


def test_spherical_angles_convention():
    r, az, el = spherical_angles(np.array([[0.0, 2.0, 0.0], [1.0, 0.0, 1.0], [-1.0, -1e-12, 0.0]]))
    np.testing.assert_allclose(r, [2.0, np.sqrt(2.0), 1.0])
    np.testing.assert_allclose(az, [90.0, 0.0, -180.0], atol=1e-9)
    np.testing.assert_allclose(el, [0.0, 45.0, 0.0], atol=1e-9)


def test_spherical_angles_may_use_up_a_column_ordered_cloud():
    """``overwrite`` on a column-ordered (n, 3) float64 cloud (how the PLY reader stores it):
    the same values with no copy of the points, the x and y columns holding azimuth and
    elevation afterwards; a row-ordered cloud is left alone (issue 16)."""
    rng = np.random.default_rng(3)
    xyz = rng.normal(0.0, 10.0, (5000, 3))
    xyz[7] = np.nan
    want = spherical_angles(xyz.copy())
    cols = np.asfortranarray(xyz)
    got = spherical_angles(cols, overwrite=True)
    for a, b in zip(want, got, strict=True):
        np.testing.assert_array_equal(a, b)
    assert np.shares_memory(got[1], cols) and np.shares_memory(got[2], cols)
    rows = xyz.copy()
    spherical_angles(rows, overwrite=True)
    np.testing.assert_array_equal(rows, xyz)


@pytest.mark.parametrize(
    "rows, cols, az_step, el_step, az0, el0",
    [
        (40, 90, 1.0, 1.0, -60.0, 20.0),
        (40, 200, 0.5, 2.0, 150.0, 38.0),  # crosses +-180 deg, anisotropic
        (30, 400, 0.45, 0.05, -170.0, 10.0),  # 9x anisotropic
    ],
)
def test_regular_grid_comes_back_exactly(rows, cols, az_step, el_step, az0, el0):
    r, az, el = grid_image(rows, cols, az_step, el_step, az0, el0)
    xyz, _ = cloud(r, az, el)
    est = estimate_angular_step(xyz)
    np.testing.assert_allclose(est, (az_step, el_step), rtol=1e-9)
    assert_same_image(project_to_range_image(xyz), r, az, el)
    given = project_to_range_image(xyz, angular_step_deg=(az_step, el_step))
    assert_same_image(given, r, az, el)


def test_full_resolution_riegl_grid_exact_and_fast():
    # spec 1.1: 3000 x 720 pixels, 0.108 x 0.1075 deg, 324 deg horizontal field of view
    r, az, el = grid_image(720, 3000, 0.108, 0.1075, -162.0, 38.7, dropout=0.05)
    xyz, _ = cloud(r, az, el)
    assert xyz.shape[0] > 2_000_000
    t0 = time.perf_counter()
    img = project_to_range_image(xyz)
    elapsed = time.perf_counter() - t0
    assert_same_image(img, r, az, el)
    assert elapsed < 10.0, f"projection of {xyz.shape[0]} points took {elapsed:.1f} s"


def test_jittered_sampling_with_dropout_has_few_holes():
    az_step, el_step = 0.36, 0.36
    r, az, el = grid_image(200, 500, az_step, el_step, -90.0, 36.0, dropout=0.0)
    xyz, keep = jittered_cloud(r, az, el, az_step, el_step, sigma=0.1, dropout=0.1)
    est = estimate_angular_step(xyz)
    np.testing.assert_allclose(est, (az_step, el_step), rtol=0.01)
    img = project_to_range_image(xyz)
    assert img.shape == r.shape
    np.testing.assert_allclose(img.azimuth_deg, az, atol=0.05 * az_step)
    # holes the projection adds (pixels whose own point was kept but came out empty)
    added = np.isnan(img.range_m[keep]).mean()
    assert added < 0.05
    # all holes inside the scanned area: the 10 % dropout plus the added ones
    assert np.isnan(img.range_m).mean() < 0.10 + 0.05
    # each kept pixel holds a point of the right range (nearest of those landing there)
    ok = keep & img.valid
    assert np.mean(np.abs(img.range_m[ok] - r[ok]) < 1e-4) > 0.95


def test_anisotropic_jitter_step_estimate():
    r, az, el = grid_image(40, 300, 0.9, 0.1, -180.0, 2.0, dropout=0.0)
    xyz, keep = jittered_cloud(r, az, el, 0.9, 0.1, sigma=0.1, dropout=0.1, seed=4)
    np.testing.assert_allclose(estimate_angular_step(xyz), (0.9, 0.1), rtol=0.01)
    img = project_to_range_image(xyz)
    assert img.shape == r.shape
    assert np.isnan(img.range_m[keep]).mean() < 0.05


def test_given_step_overrides_estimate():
    r, az, el = grid_image(40, 90, 1.0, 1.0, -60.0, 20.0, dropout=0.0)
    xyz, _ = cloud(r, az, el)
    coarse = project_to_range_image(xyz, angular_step_deg=2.0)
    assert coarse.shape == (20, 45)
    assert coarse.azimuth_step_deg == pytest.approx(2.0)
    assert coarse.elevation_step_deg == pytest.approx(2.0)
    assert coarse.valid.all()  # each 2 x 2 block of points fills one pixel
    # per pixel a point of its 2 x 2 block's front surface (first return: within 0.11 m of
    # the nearest; of those the one nearest the pixel centre)
    blocks = r.reshape(20, 2, 45, 2)
    assert (coarse.range_m - blocks.min(axis=(1, 3)) <= 0.11 + 1e-5).all()
    assert np.isclose(blocks, coarse.range_m[:, None, :, None], rtol=1e-6).any(axis=(1, 3)).all()
    fine = project_to_range_image(xyz, angular_step_deg=(0.5, 1.0))
    assert fine.shape == (40, 179)
    assert fine.valid.sum() == np.isfinite(r).sum()
    assert not fine.valid[:, 1::2].any()  # the half-step columns are empty, as asked


def test_wrap_around_330_degree_scan_not_split():
    # 330 deg of azimuth from 100 deg through 180/-180 to 70 deg; the gap is 70..100
    r, az, el = grid_image(20, 331, 1.0, 1.0, 100.0, 10.0)
    xyz, _ = cloud(r, az, el)
    img = project_to_range_image(xyz)
    assert img.shape == (20, 331)
    assert np.all(np.diff(img.azimuth_deg) > 0)
    assert img.azimuth_deg[0] == pytest.approx(100.0, abs=1e-8)
    assert img.azimuth_deg[-1] == pytest.approx(430.0, abs=1e-8)
    assert_same_image(img, r, az, el)
    # a gap straddling the +-180 seam instead: the image starts after it, at -170 deg
    r2, az2, el2 = grid_image(20, 331, 1.0, 1.0, -170.0, 10.0, seed=2)
    img2 = project_to_range_image(cloud(r2, az2, el2)[0])
    assert_same_image(img2, r2, az2, el2)


def test_full_circle_scan_is_one_rotation_of_the_columns():
    r, az, el = grid_image(10, 360, 1.0, 1.0, -180.0, 5.0, dropout=0.0)
    img = project_to_range_image(cloud(r, az, el)[0])
    assert img.shape == (10, 360)
    shift = int(np.argmin(np.abs(((az - img.azimuth_deg[0]) + 180) % 360 - 180)))
    np.testing.assert_allclose(img.range_m, np.roll(r, -shift, axis=1), rtol=1e-6)


def test_nearest_point_wins_and_keeps_its_colour_and_intensity():
    r, az, el = grid_image(10, 20, 1.0, 1.0, 0.0, 5.0, dropout=0.0)
    xyz, _ = cloud(r, az, el)
    n = xyz.shape[0]
    rgb = np.tile(np.array([[10, 20, 30]], dtype=np.uint8), (n, 1))
    inten = np.full(n, 1.0, dtype=np.float32)
    # behind every point a second return in the same direction, other colour and intensity
    far = xyz * 1.5
    img = project_to_range_image(
        np.vstack([far, xyz]),
        rgb=np.vstack([np.full((n, 3), 200, np.uint8), rgb]),
        intensity=np.concatenate([np.full(n, 9.0, np.float32), inten]),
    )
    np.testing.assert_allclose(img.range_m, r, rtol=1e-6)
    assert (img.rgb == [10, 20, 30]).all()
    assert (img.intensity == 1.0).all()


def test_nearest_per_pixel_picks_min_range():
    flat = np.array([3, 1, 3, 3, 1, 7])
    rng = np.array([5.0, 2.0, 1.5, 9.0, 4.0, 3.0])
    kept = nearest_per_pixel(flat, rng)
    assert sorted(kept.tolist()) == [1, 2, 5]


def test_invalid_points_dropped_and_bad_input_rejected():
    r, az, el = grid_image(10, 20, 1.0, 1.0, 0.0, 5.0, dropout=0.0)
    xyz, _ = cloud(r, az, el)
    noisy = np.vstack([xyz, [[np.nan, 1.0, 1.0], [0.0, 0.0, 0.0], [np.inf, 0, 0]]])
    assert_same_image(project_to_range_image(noisy), r, az, el)
    with pytest.raises(ValueError, match="xyz"):
        project_to_range_image(np.zeros((5, 2)))
    with pytest.raises(ValueError, match="rgb"):
        project_to_range_image(xyz, rgb=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="angular_step_deg"):
        project_to_range_image(xyz, angular_step_deg=-1.0)
    with pytest.raises(ValueError, match="no valid points"):
        project_to_range_image(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="fewer than 2"):
        estimate_angular_step(xyz[:1])
    with pytest.raises(ValueError, match="pixels"):
        project_to_range_image(xyz, angular_step_deg=1e-4)


def test_sparse_sampling_half_the_returns_missing():
    # 50 % dropout: nearest neighbours are often two steps away; the estimate must not drift
    az_step = el_step = 0.3
    r, az, el = grid_image(130, 400, az_step, el_step, -60.0, 20.0, dropout=0.0)
    xyz, keep = jittered_cloud(r, az, el, az_step, el_step, sigma=0.1, dropout=0.5, seed=7)
    np.testing.assert_allclose(estimate_angular_step(xyz), (az_step, el_step), rtol=0.002)
    img = project_to_range_image(xyz, min_fill=0.0)  # the scanner's own grid, half empty
    assert img.shape == r.shape
    assert np.isnan(img.range_m[keep]).mean() < 0.05
    assert fill_ratio(img.valid) < 0.55
    # by default the step grows until the region and the returns' neighbourhoods are mostly
    # filled (half the returns missing leaves every surface holey); more with a higher min_fill
    grown = project_to_range_image(xyz)
    assert fill_ratio(grown.valid) >= 0.5 and neighbour_fill(grown.valid) >= 0.7
    assert 1.05 < grown.azimuth_step_deg / az_step < 1.5
    filled = project_to_range_image(xyz, min_fill=0.7)
    assert fill_ratio(filled.valid) >= 0.7
    assert 1.05 < filled.azimuth_step_deg / az_step < 1.5
    assert filled.elevation_step_deg / filled.azimuth_step_deg == pytest.approx(1.0, rel=0.01)


def test_pixels_keep_their_points_own_xyz():
    # points off any grid (a sampled scene): every pixel keeps one input point exactly, never
    # one re-synthesised at the pixel's centre (issue 18), also through the stored table
    from dataclasses import replace

    from forestmap_assets.core.features.range_image import RangeImage

    rng = np.random.default_rng(3)
    n = 40_000
    a, e = np.radians(rng.uniform(-40, 40, n)), np.radians(rng.uniform(-20, 20, n))
    r = rng.uniform(2.0, 30.0, n)
    xyz = np.column_stack([r * np.cos(e) * np.cos(a), r * np.cos(e) * np.sin(a), r * np.sin(e)])
    img = project_to_range_image(xyz)
    assert img.points is not None and fill_ratio(img.valid) >= 0.5
    kept = img.xyz[img.valid]
    d, _ = cKDTree(xyz).query(kept)
    assert d.max() < 1e-5
    np.testing.assert_allclose(np.linalg.norm(kept, axis=1), img.range_m[img.valid], rtol=1e-6)
    tilted = replace(img, tilt_deg=(1.5, -2.0), _xyz=None)
    back = RangeImage.from_table(tilted.to_table())
    np.testing.assert_allclose(back.points[img.valid], img.points[img.valid], atol=2e-5)
    np.testing.assert_allclose(back.xyz[img.valid], tilted.xyz[img.valid], atol=2e-5)


def test_coarse_step_does_not_widen_a_stem():
    # a 20 cm stem 8 m away sampled at random on its visible half, projected at 0.3 deg (4 cm
    # pixels): its points stay on the stem (pixel-centre angles would put the silhouette's
    # edge pixels up to 2 cm outside it and move the circle centre away from the scanner)
    rng = np.random.default_rng(5)
    n, radius, centre = 30_000, 0.1, np.array([8.0, 0.0])
    theta = np.pi + rng.uniform(-np.pi / 2, np.pi / 2, n)
    xyz = np.column_stack([centre[0] + radius * np.cos(theta), radius * np.sin(theta),
                           rng.uniform(-1.0, 1.0, n)])
    img = project_to_range_image(xyz, angular_step_deg=0.3)
    pts = img.xyz[img.valid]
    off_axis = np.hypot(pts[:, 0] - centre[0], pts[:, 1] - centre[1])
    np.testing.assert_allclose(off_axis, radius, atol=1e-5)
