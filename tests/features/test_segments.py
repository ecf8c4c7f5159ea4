"""Scan-line segmentation (spec 2, Table 4.1, validation targets 13.13-13.14)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from helpers.synthetic import Cylinder, Scene, Wall, grid, render

from forestmap_assets.core.features.circle_models import final_circles, fit_circle_models
from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.core.features.segments import (
    SEGMENT_COLUMNS,
    blocking_max_filter,
    feature_scan_lines,
    occluder_window,
    segment_mask,
    segment_pixels,
    segment_scan_lines,
)
from forestmap_assets.params import SegmentationParams

STEP = np.radians(0.108)


def _image(scene, az=(-8, 8), el=(-5, 15), noise=0.0, seed=0):
    a, e = grid(az, el)
    img, truth = render(scene, a, e, noise_m=noise, seed=seed)
    return img, truth


def test_occluder_window_is_odd_count_covering_the_occluder():
    r = np.array([[10.0, 2.0, 0.5, np.nan]])
    w = occluder_window(r, np.array([0.0]), STEP, 0.04)
    # 0.04 / (r * 0.001885) + 1 -> 3.12, 11.6, 43.4 -> odd ceilings 5, 13, 45; no return -> 1
    assert w.tolist() == [[5, 13, 45, 1]]
    # horizontal pitch shrinks with cos(elevation): wider window at 60 deg
    assert occluder_window(np.array([[10.0]]), np.array([60.0]), STEP, 0.04)[0, 0] == 7


def test_blocking_max_filter_equals_brute_force():
    rng = np.random.default_rng(3)
    r = rng.uniform(1, 30, (7, 60)).astype(np.float32)
    r[rng.random(r.shape) < 0.1] = np.nan
    w = rng.choice([1, 3, 5, 7, 9, 13, 21], size=r.shape)
    got = blocking_max_filter(r, w)
    want = np.full(r.shape, np.nan, np.float32)
    for i in range(r.shape[0]):
        for j in range(r.shape[1]):
            if np.isfinite(r[i, j]):
                h = w[i, j] // 2
                want[i, j] = np.nanmax(r[i, max(j - h, 0):j + h + 1])
    np.testing.assert_array_equal(got, want)


def _trunk_with_branch(branch_radius):
    trunk = Cylinder((8.0, 0.0, -1.5), (0, 0, 1), 0.15, 6.0)  # 0.30 m wide trunk at 8 m
    branch = Cylinder((6.0, 0.0, -1.5), (0, 0, 1), branch_radius, 6.0)  # in front of it
    return _image(Scene([trunk, branch], ground_z=None), az=(-3, 3), el=(0, 10))[0]


def test_thin_occluder_does_not_split_the_trunk_but_a_wide_one_does():
    """Validation target 13.13: a 0.03 m branch keeps one segment, a 0.06 m one splits it."""
    p = SegmentationParams()
    thin = segment_scan_lines(_trunk_with_branch(0.015), p)
    per_row = thin.groupby("row").size()
    assert (per_row == 1).all() and len(per_row) == thin["row"].nunique() > 80
    # the branch hits are outliers of the T_out gate, not inliers of the trunk segment
    img = _trunk_with_branch(0.015)
    _, pr, pc, _ = segment_pixels(img, thin)
    assert np.all(img.range_m[pr, pc] > 7.5)
    wide = segment_scan_lines(_trunk_with_branch(0.03), p)
    trunk_rows = wide[wide["r_mid"] > 7.5].groupby("row").size()
    assert (trunk_rows == 2).mean() > 0.95


def test_width_and_point_count_bounds():
    """Validation target 13.14: W outside [0.06, 1.0] m or < 4 points is rejected."""
    p = SegmentationParams()
    objs = [Cylinder((6.0, -1.0, -1.5), (0, 0, 1), 0.02, 5.0),  # 0.04 m: too narrow
            Cylinder((6.0, 0.0, -1.5), (0, 0, 1), 0.1, 5.0),  # 0.20 m: accepted
            Cylinder((6.0, 1.6, -1.5), (0, 0, 1), 0.6, 5.0),  # 1.2 m: too wide
            Cylinder((20.0, 6.0, -1.5), (0, 0, 1), 0.035, 5.0)]  # 0.07 m at 21 m: < 4 points
    img, _ = _image(Scene(objs, ground_z=None), az=(-20, 25), el=(0, 8))
    seg = segment_scan_lines(img, p)
    assert len(seg) > 0
    assert seg["width_m"].between(p.min_width_m, p.max_width_m).all()
    assert (seg["n_inliers"] >= p.min_points).all()
    az_mid = seg["azimuth_mid_deg"].to_numpy()
    accepted = np.degrees(np.arctan2(0.0, 6.0))
    assert np.all(np.abs(az_mid - accepted) < 1.5)
    assert seg["width_m"].median() == pytest.approx(0.2, abs=0.02)


def test_ground_and_walls_give_no_segments():
    p = SegmentationParams()
    ground, _ = _image(Scene(), az=(-60, 60), el=(-30, -3), noise=0.025)
    assert len(segment_scan_lines(ground, p)) == 0
    walls = Scene(walls=[Wall(6, -8, 6, 8), Wall(-3, 5, 6, 5)], ground_z=-1.5)
    img, _ = _image(walls, az=(-30, 60), el=(-10, 10), noise=0.025)
    assert len(segment_scan_lines(img, p)) == 0


def test_outlier_gate_and_mask():
    """Inliers are exactly the returns of [col0, col1] within T_out = 0.5 W + 3 sigma (Eq. 4.7)."""
    p = SegmentationParams()
    img, _ = _image(Scene([Cylinder((5.0, 0.0, -1.5), (0, 0, 1), 0.2, 5.0)]), az=(-5, 5),
                    el=(-2, 6), noise=0.025, seed=1)
    seg = segment_scan_lines(img, p)
    np.testing.assert_allclose(seg["t_out_m"], 0.5 * seg["width_m"] + 3 * 0.025)
    mask = segment_mask(img, seg)
    s, pr, pc, inl = segment_pixels(img, seg, inliers_only=False)
    r_mid = seg["r_mid"].to_numpy()[s]
    expect = np.abs(img.range_m[pr, pc] - r_mid) <= seg["t_out_m"].to_numpy()[s]
    np.testing.assert_array_equal(inl, expect)
    assert mask.sum() == inl.sum() == seg["n_inliers"].sum()
    # the trunk is 0.4 m wide: W close to it, r_mid near the front surface
    assert seg["width_m"].median() == pytest.approx(0.4, abs=0.03)
    assert np.median(seg["r_mid"] / np.cos(np.radians(seg["elevation_deg"]))) == \
        pytest.approx(4.8, abs=0.06)


def test_vertical_chains():
    """One chain per stem; a stem right behind another (same columns, > 0.11 m farther) is a
    separate chain (spec 2.4)."""
    p = SegmentationParams()
    front = Cylinder((5.0, 0.0, -1.5), (0, 0, 1), 0.15, 3.0)  # ends at z = 1.5
    back = Cylinder((9.0, 0.05, -1.5), (0, 0, 1), 0.3, 8.0)  # wider, visible around/above
    img, _ = _image(Scene([front, back], ground_z=None), az=(-5, 5), el=(-5, 25), noise=0.01)
    seg = segment_scan_lines(img, p)
    near = seg[seg["r_mid"] < 6]
    assert near["chain_id"].nunique() == 1
    assert near["row"].nunique() == len(near) > 100
    assert not set(near["chain_id"]) & set(seg.loc[seg["r_mid"] > 8, "chain_id"])


def test_empty_inputs_give_well_formed_empty_tables():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for img in (RangeImage(np.zeros((0, 0), np.float32), np.zeros(0), np.zeros(0)),
                    RangeImage(np.full((5, 9), np.nan, np.float32), np.arange(9.0), -np.arange(5.0))):
            seg = segment_scan_lines(img)
            assert len(seg) == 0
            assert dict(seg.dtypes.astype(str)) == SEGMENT_COLUMNS
            assert segment_mask(img, seg).shape == img.shape


def test_scan_lines_closer_than_the_line_step_are_thinned_and_the_stem_kept():
    """``segmentation.min_line_step_deg`` (issue 16): a 0.05 deg scan keeps every 4th row for
    the segments and circle models, the thesis' 0.108 deg every row; the stem's circles on the
    thinned rows give its radius as the full rows do, from a quarter of the circles."""
    stem = Cylinder((8.0, 0.0, -1.5), (0, 0, 1), 0.15, 6.0)
    scene = Scene([stem], ground_z=None)
    a, e = grid((-4, 4), (-5, 20), step_deg=0.05)
    img, _ = render(scene, a, e, noise_m=0.005)
    step = SegmentationParams().min_line_step_deg
    thin = feature_scan_lines(img, step)
    assert thin.shape == (len(img.elevation_deg[::4]), img.shape[1])
    np.testing.assert_array_equal(thin.elevation_deg, img.elevation_deg[::4])
    np.testing.assert_array_equal(thin.range_m, img.range_m[::4])
    assert feature_scan_lines(img, 0.0) is img
    a108, e108 = grid((-4, 4), (-5, 20), step_deg=0.108)
    img108, _ = render(scene, a108, e108, noise_m=0.005)
    assert feature_scan_lines(img108, step) is img108
    radii = {}
    for name, im in (("full", img), ("thin", thin)):
        fin = final_circles(fit_circle_models(im, segment_scan_lines(im)))
        radii[name] = fin.loc[fin["valid"], "radius_m"].to_numpy()
    assert 3.5 < radii["full"].size / radii["thin"].size < 4.5
    for r in radii.values():
        assert abs(np.median(r) - 0.15) < 0.003
