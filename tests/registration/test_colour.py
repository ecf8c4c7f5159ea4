"""Colour: HSL hue (men spec 2.6), hue filter/histogram, colour kept through range images, and
the simulator's colour model (hue stable across viewpoints, RGB not)."""

from __future__ import annotations

import colorsys

import numpy as np
import pytest

from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.core.registration.colour import (
    hsl_to_rgb,
    hue_features,
    hue_filter,
    hue_histogram,
    image_hue,
    rgb_to_hsl,
    rgb_to_hue,
    table_hue,
)
from forestmap_assets.sim.scene_mesh import KIND_FOLIAGE, KIND_GROUND, KIND_STEM


def test_table_5_1_hues_grey_zero_and_red_at_an_end():
    rgb = np.array([[128, 128, 128], [255, 255, 0], [0, 255, 0], [0, 255, 255], [0, 0, 255],
                    [255, 0, 255], [255, 0, 0]], dtype=np.uint8)
    h = rgb_to_hue(rgb)
    np.testing.assert_allclose(h[:6], [0, 60 / 360, 120 / 360, 180 / 360, 240 / 360, 300 / 360], atol=1e-12)
    assert h[6] in (0.0, 1.0)  # Table 5.1 prints 360 deg; linear hue has no wrap (spec 2.6)


def test_hsl_matches_colorsys_and_round_trips():
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (500, 3)).astype(np.uint8)
    h, s, light = rgb_to_hsl(rgb)
    ref = np.array([colorsys.rgb_to_hls(*(c / 255.0)) for c in rgb])
    np.testing.assert_allclose(h, ref[:, 0], atol=1e-12)
    np.testing.assert_allclose(light, ref[:, 1], atol=1e-12)
    np.testing.assert_allclose(s, ref[:, 2], atol=1e-12)
    np.testing.assert_allclose(hsl_to_rgb(h, s, light) * 255.0, rgb, atol=1e-9)
    # float input in [0, 1] and uint16 give the same hue as uint8
    np.testing.assert_allclose(rgb_to_hue(rgb / 255.0), h, atol=1e-12)
    np.testing.assert_allclose(rgb_to_hue(rgb.astype(np.uint16) * 257), h, atol=1e-12)


def test_hue_invariant_to_lightness_scaling_unlike_rgb():
    base = np.array([[120, 80, 40], [40, 110, 60], [70, 70, 160]], dtype=np.float64)
    darker = np.rint(base * 0.6)
    assert np.abs(base - darker).max() > 40
    np.testing.assert_allclose(rgb_to_hue(darker.astype(np.uint8)), rgb_to_hue(base.astype(np.uint8)), atol=0.01)


def test_hue_features_filter_and_histogram():
    h = np.array([0.0, 0.1, 0.5, 0.51, 0.999])
    assert hue_filter(h).tolist() == [True, True, True, False, False]
    hist = hue_histogram(h, bins=10)
    assert hist["count"].sum() == 5 and hist["count"].iloc[0] == 1 and hist["count"].iloc[9] == 1
    assert hue_features(h).shape == (5, 1)
    circ = hue_features(np.array([0.001, 0.999]), "circular")
    assert np.linalg.norm(circ[0] - circ[1]) < 0.003  # red near 0 and near 1 are neighbours
    with pytest.raises(ValueError, match="hue mode"):
        hue_features(h, "polar")


def test_hue_computed_from_range_image_table_and_image():
    rng = np.random.default_rng(1)
    r = rng.uniform(2, 10, (6, 8)).astype(np.float32)
    r[0, 0] = np.nan
    rgb = rng.integers(0, 256, (6, 8, 3)).astype(np.uint8)
    img = RangeImage(r, np.linspace(-20, 20, 8), np.linspace(10, -10, 6), rgb=rgb)
    table = img.to_table().to_pandas()
    hue = table_hue(table)
    np.testing.assert_allclose(hue, rgb_to_hue(rgb[img.valid]))
    back = RangeImage.from_table(img.to_table())
    hi = image_hue(back)
    assert np.isnan(hi[0, 0]) and np.allclose(hi[img.valid], hue)
    assert table_hue(table.drop(columns=["r", "g", "b"])) is None
    assert image_hue(RangeImage(r, img.azimuth_deg, img.elevation_deg)) is None


def test_simulated_colour_hue_stable_across_scans_rgb_not():
    from forestmap_assets.sim import ScanPose, VirtualScanner, make_forest

    forest = make_forest(12, 20.0, n_scans=2, seed=4)
    plain = VirtualScanner(forest, resolution="quarter")
    scanner = VirtualScanner(forest, resolution="quarter", colour=True)
    poses = []
    for i, (x, y) in enumerate(forest.scan_xy):
        poses.append(ScanPose(float(x), float(y), float(forest.ground.height(x, y) + 1.5), 40.0 * i - 20.0))
    a, b = (scanner.scan(p, seed=i) for i, p in enumerate(poses))
    # colour does not change the geometry or its noise
    np.testing.assert_array_equal(plain.scan(poses[0], seed=0).image.range_m, a.image.range_m)
    assert a.image.rgb is not None and a.image.rgb.shape == a.image.range_m.shape + (3,)
    assert not a.image.rgb[~a.image.valid].any()
    ha = rgb_to_hue(a.image.rgb)
    for kind, lo, hi in ((KIND_STEM, 0.02, 0.2), (KIND_FOLIAGE, 0.18, 0.4), (KIND_GROUND, 0.04, 0.3)):
        med = np.median(ha[a.kind == kind])
        assert lo < med < hi, (kind, med)
    # the same ground surface seen from both scans: nearest points within 2 cm
    from scipy.spatial import cKDTree

    pa, pb = a.world_points(noisy=False), b.world_points(noisy=False)
    sel_a = a.kind == KIND_GROUND
    sel_b = b.kind == KIND_GROUND
    tree = cKDTree(pb[sel_b])
    d, j = tree.query(pa[sel_a], distance_upper_bound=0.02)
    ok = np.isfinite(d)
    assert ok.sum() > 200
    hb = rgb_to_hue(b.image.rgb)[sel_b][j[ok]]
    rgb_a = a.image.rgb[sel_a][ok].astype(float)
    rgb_b = b.image.rgb[sel_b][j[ok]].astype(float)
    dh = np.abs(ha[sel_a][ok] - hb)
    # hue of the same surface agrees closely; RGB differs by the scans' light (spec 2.6)
    assert np.median(dh) < 0.02
    rel_rgb = np.median(np.abs(rgb_a - rgb_b).sum(axis=1) / np.maximum(rgb_a.sum(axis=1), 1))
    assert rel_rgb > 3 * np.median(dh)
    # hue varies over the ground (moss/litter patches), so it can guide matching
    assert np.percentile(ha[sel_a], 90) - np.percentile(ha[sel_a], 10) > 0.05


def test_simulated_colour_campaign_keeps_rgb_through_the_reader(tmp_path):
    from forestmap_assets.io.readers import read_scan
    from forestmap_assets.sim import simulate_campaign

    out = simulate_campaign(tmp_path / "c", scans=2, trees=8, plot_size=20.0, resolution="quarter",
                            fmt="e57", scanner_kwargs={"colour": True}, write_labels=False)
    img = read_scan(out / "scans" / "T.e57")
    assert img.rgb is not None
    hue = rgb_to_hue(img.rgb[img.valid])
    assert 0.04 < np.median(hue) < 0.35
