"""Occlusion boundaries on organised range images (men_spec 3.1; validation targets V3, V4)."""

from __future__ import annotations

import numpy as np
import pytest

from forestmap_assets.core.exploration.occlusion import (
    boundaries_table,
    detect_occlusions,
    occlusion_threshold,
    pair_angles_deg,
    pair_masks,
    range_variance,
)
from forestmap_assets.core.features.range_image import RangeImage

STEP = 0.25  # deg, the thesis's scanner


def _rays(az_deg: np.ndarray, el_deg: np.ndarray) -> np.ndarray:
    a, e = np.meshgrid(np.radians(az_deg), np.radians(el_deg))
    return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1)


def _plane_range(d: np.ndarray, normal, offset: float) -> np.ndarray:
    """Range to the plane n.p = offset along unit rays d (NaN where it is behind)."""
    n = np.asarray(normal, dtype=float)
    n = n / np.linalg.norm(n)
    with np.errstate(divide="ignore"):
        r = offset / (d @ n)
    return np.where(r > 0, r, np.nan)


def _wall_image(step=STEP, az=(-30.0, 30.0), el=(25.0, -25.0)):
    azimuth = np.arange(az[0], az[1] + 1e-9, step)
    elevation = np.arange(el[0], el[1] - 1e-9, -step)
    d = _rays(azimuth, elevation)
    return azimuth, elevation, d, _plane_range(d, (1, 0, 0), 10.0)


def _silhouette_neighbours(label: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels with a 4-neighbour of another object, in the tilt (rows) and pan (cols) direction."""
    tilt = np.zeros_like(label, dtype=bool)
    pan = np.zeros_like(label, dtype=bool)
    dv = label[:-1] != label[1:]
    du = label[:, :-1] != label[:, 1:]
    tilt[:-1] |= dv
    tilt[1:] |= dv
    pan[:, :-1] |= du
    pan[:, 1:] |= du
    return tilt, pan


def test_v3_threshold_value():
    assert occlusion_threshold(0.25, 5.0) == pytest.approx(0.05269, abs=1e-4)
    # grows sharply as the step approaches the threshold angle, none beyond it
    assert occlusion_threshold(1.0, 5.0) > 4 * occlusion_threshold(0.25, 5.0)
    assert np.isinf(occlusion_threshold(6.0, 5.0))


def test_v4_flat_wall_has_no_boundary():
    # incidence 90 deg +- 40 deg: cos(az) cos(el) >= cos(40 deg) over the whole image
    az, el, d, r = _wall_image()
    assert (d[..., 0] >= np.cos(np.radians(40.0)) - 1e-12).all()
    ob = detect_occlusions(RangeImage(r, az, el))
    assert ob.boundary[1:-1, 1:-1].sum() == 0
    assert ob.boundary.sum() == 0
    # the ratios are the spacing of a surface seen head-on, ~Delta in radians
    assert np.nanmax(ob.tilt_ratio) < 0.2 * occlusion_threshold(STEP)


def test_v4_box_in_front_of_wall_recall_and_false_positives():
    az, el, d, r = _wall_image()
    t = 6.0 / d[..., 0]  # box front face at x = 6 m
    p = t[..., None] * d
    box = (np.abs(p[..., 1]) <= 1.0) & (p[..., 2] >= -0.5) & (p[..., 2] <= 1.0)
    rng = np.where(box, t, r)
    ob = detect_occlusions(RangeImage(rng, az, el))
    tilt_adj, pan_adj = _silhouette_neighbours(box)
    assert tilt_adj.sum() > 50 and pan_adj.sum() > 50
    # far-surface and near-edge sides flagged, in both directions
    assert ob.tilt[tilt_adj].mean() >= 0.95
    assert ob.pan[pan_adj].mean() >= 0.95
    assert ob.near[box & (tilt_adj | pan_adj)].mean() >= 0.95
    assert ob.far[~box & (tilt_adj | pan_adj)].mean() >= 0.95
    interior = ~(tilt_adj | pan_adj)
    assert ob.boundary[interior].mean() <= 0.01
    # the range-variance test finds the same silhouette (a 4 m jump)
    v = range_variance(rng)
    assert (v[tilt_adj | pan_adj] > 3.5).all() and (v[interior] < 0.1).all()
    assert ob.variance[tilt_adj | pan_adj].all()


@pytest.mark.parametrize("direction", ["pan", "tilt"])
def test_v4_grazing_plane_flagged_below_5_deg_not_at_10(direction):
    az = np.arange(-0.75, 0.75 + 1e-9, STEP)
    el = np.arange(0.75, -0.75 - 1e-9, -STEP)
    d = _rays(az, el)
    flagged = {}
    for alpha in (4.0, 10.0):
        a = np.radians(alpha)
        # plane whose angle with the central ray is alpha, tilted in the tested direction
        normal = (
            (np.sin(a), -np.cos(a), 0.0) if direction == "pan" else (np.sin(a), 0.0, -np.cos(a))
        )
        r = _plane_range(d, normal, 5.0 * np.sin(a))  # the central ray meets it at 5 m
        assert np.isfinite(r).all()
        ob = detect_occlusions(RangeImage(r, az, el))
        flagged[alpha] = getattr(ob, direction)
        other = ob.tilt if direction == "pan" else ob.pan
        assert not other.any()  # the other direction sees the plane head-on
    assert flagged[4.0].all()
    assert not flagged[10.0].any()


def test_thesis_cutoff_and_exact_pan_angles():
    az = np.arange(0.0, 10.0, STEP)
    el = np.array([60.0, 60.0 - STEP])
    d_tilt, d_pan = pair_angles_deg(az, el)
    assert np.allclose(d_tilt, STEP)
    # neighbouring columns 60 deg above the horizon are only cos(60) * 0.25 deg apart
    assert np.allclose(d_pan[0], STEP * 0.5, rtol=1e-3)
    _, nominal = pair_angles_deg(az, el, exact=False)
    assert np.allclose(nominal, STEP)
    # the fixed cutoff of the thesis (0.05) is accepted instead of the computed threshold
    azw, elw, _, r = _wall_image()
    ob = detect_occlusions(RangeImage(r, azw, elw), ratio_cutoff=0.001)
    assert ob.boundary.all()  # every head-on pair exceeds a tiny cutoff


def test_missing_returns_and_combine_rules():
    az, el, d, r = _wall_image()
    r = r.copy()
    r[:40] = np.nan  # sky: no returns is not an object occlusion
    r[100:104, 100:104] += 0.2  # a 0.2 m step at 10 m
    ob_s = detect_occlusions(RangeImage(r, az, el), combine="spacing")
    assert not ob_s.boundary[:40].any()
    assert not ob_s.boundary[40, :].any()  # the row next to the sky has no flagged pair
    # spacing / r of the 0.2 m step is 0.02: above a head-on surface (0.004), below 0.053
    assert not ob_s.boundary[99:105, 99:105].any()
    ob_v = detect_occlusions(RangeImage(r, az, el), combine="variance", variance_threshold_m=0.1)
    assert ob_v.boundary[99:105, 99:105].any() and ob_v.boundary.sum() == ob_v.variance.sum()
    ob_b = detect_occlusions(RangeImage(r, az, el), combine="both", variance_threshold_m=0.1)
    assert ob_b.boundary.sum() == 0
    ob_e = detect_occlusions(RangeImage(r, az, el), combine="either", variance_threshold_m=0.1)
    assert ob_e.boundary.sum() == ob_v.boundary.sum()


def test_boundaries_table_round_trip_of_pair_masks():
    az, el, d, r = _wall_image()
    t = 6.0 / d[..., 0]
    p = t[..., None] * d
    box = (np.abs(p[..., 1]) <= 1.0) & (p[..., 2] >= -0.5) & (p[..., 2] <= 1.0)
    image = RangeImage(np.where(box, t, r), az, el)
    ob = detect_occlusions(image)
    table = boundaries_table(image, ob)
    assert len(table) == int((ob.boundary | ob.variance).sum())
    assert table[["x", "y", "z"]].notna().all().all()
    assert (table["ratio"][table["tilt"] | table["pan"]] >= 0.05).all()
    tilt, pan = pair_masks(table, image.shape)
    assert np.array_equal(tilt, ob.tilt_pair) and np.array_equal(pan, ob.pan_pair)


def test_full_circle_wraps_the_last_column():
    az = np.arange(-180.0, 180.0, 1.0)
    el = np.arange(10.0, -10.0 - 1e-9, -1.0)
    d = _rays(az, el)
    r = np.full(d.shape[:2], 10.0)
    r[:, -1] = 5.0  # a post in the last column only; its other neighbour is column 0
    ob = detect_occlusions(RangeImage(r, az, el))
    assert ob.wrap and ob.pan[:, 0].all() and ob.pan[:, -2].all() and ob.pan[:, -1].all()
    assert not ob.pan[:, 1:-2].any()
