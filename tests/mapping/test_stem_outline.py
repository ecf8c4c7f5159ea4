"""One outline through the merged slice and the silhouette sides (core/mapping/stem_outline.py)."""

from __future__ import annotations

import numpy as np
import pandas as pd
from test_stem_slices import outline, scan_section

from forestmap_assets.core.mapping.stem_calipers import _side_weights
from forestmap_assets.core.mapping.stem_outline import blend_outline, outline_dbhs
from forestmap_assets.core.mapping.stem_slices import slice_dbh
from forestmap_assets.params import TreeParams

R, C, THETA = 0.18, 0.04, 0.7  # mean radius, out-of-roundness, its orientation
SENSORS = [12.0 * np.array([np.cos(a), np.sin(a)]) for a in np.radians([160.0, 180.0, 200.0])]


def support(phi, centre=(0.0, 0.0)):
    """The section's tangent distance from ``centre`` along the outward normal ``phi``."""
    psi = np.linspace(-np.pi, np.pi, 4000, endpoint=False)
    r = outline(R, C, THETA, psi)
    p = np.column_stack([r * np.cos(psi), r * np.sin(psi)]) - np.asarray(centre)
    n = np.column_stack([np.cos(phi), np.sin(phi)])
    return (n @ p.T).max(axis=1)


def one_sided_stem(rng, start):
    """Slice points of three scans on one side of the stem, and one side a scan (the other
    hidden), its distance from ``start`` within a 4 mm pixel."""
    xy = np.vstack([scan_section((0.0, 0.0), R, C, THETA, s, rng, sigma=0.01, mixed=False) for s in SENSORS])
    sens = np.repeat(np.asarray(SENSORS), len(xy) // 3, axis=0)
    los = np.array([np.arctan2(-s[1], -s[0]) for s in SENSORS])
    phi = los + np.pi / 2
    h = support(phi, start) + rng.uniform(-0.002, 0.002, phi.size)
    return xy, sens, phi, h


def test_one_sided_stem_from_its_front_arcs_and_single_sides():
    """Scans from one side: the slice alone sees too little of the circumference, and a single
    side's distance from an axis the arcs pulled off reads the radius centimetres wrong; the
    arcs' symmetry places the centre and the sides then fix the radius."""
    rng = np.random.default_rng(3)
    start = np.array([-0.04, 0.03])  # axis pulled towards the scanners and across
    xy, sens, phi, h = one_sided_stem(rng, start)
    alone = slice_dbh(xy, sens, tuple(start), 0.15, min_coverage_deg=180.0, beam_exit_m=0.0,
                      beam_divergence_rad=0.0)
    assert np.isnan(alone.dbh_m) and "circumference" in alone.reason
    assert abs(2 * h.mean() - 2 * R) > 0.02
    w = np.full(phi.size, 1.0 / (0.004**2 / 12 + 0.004**2))
    fit = slice_dbh(xy, sens, tuple(start), 0.15, min_coverage_deg=0.0, beam_exit_m=0.0, beam_divergence_rad=0.0,
                    sides=(phi, h, w))
    assert abs(fit.dbh_m - 2 * R) < 0.006
    assert np.hypot(fit.x, fit.y) < 0.01
    assert 0 < fit.sd_m < 0.02


def test_outline_blend_weights_by_its_own_sd():
    """outline_dbhs fits each stem with sides; blend_outline moves the DBH so far towards it by
    ref^2 / (ref^2 + sd^2) and says so; a stem without sides keeps its DBH."""
    rng = np.random.default_rng(4)
    start = np.array([-0.04, 0.03])
    xy, sens, phi, h = one_sided_stem(rng, start)
    stems = pd.DataFrame({"x": [start[0], 5.0], "y": [start[1], 5.0], "zbh": 1.3, "radius_m": [0.15, 0.1],
                          "slope_x": 0.0, "slope_y": 0.0})
    sensors = np.asarray(SENSORS)
    slices = pd.DataFrame({"tree": 0, "x": xy[:, 0], "y": xy[:, 1], "z": 1.3,
                           "scan": np.repeat(np.arange(3), len(xy) // 3)})
    sides = pd.DataFrame({"tree": 0, "scan": ["a", "b", "c"], "side": 1, "h": h, "size": 20,
                          "quantum": 0.004, "phi": phi})
    tp = TreeParams(beam_exit_m=0.0, beam_divergence_mrad=0.0)
    sides = sides.assign(w=tp.outline_side_weight * _side_weights(sides, tp.caliper_width_sd_m))
    fitted = outline_dbhs(stems, slices, sensors, sides, tp)
    assert fitted["tree"].tolist() == [0]
    assert abs(fitted["outline_dbh_m"].iat[0] - 2 * R) < 0.008  # one-sided ellipse: +0.2-0.5 cm
    trees = pd.DataFrame({"tree_id": [1, 2], "dbh_m": [0.30, 0.20], "dbh_note": ["", ""]})
    fits = pd.DataFrame({"tree_id": [1, 2]})
    out, fits = blend_outline(trees, fits, fitted, tp.outline_ref_sd_m)
    sd = fitted["outline_sd_m"].iat[0]
    w = tp.outline_ref_sd_m**2 / (tp.outline_ref_sd_m**2 + sd**2)
    assert 0.2 < w < 1.0
    assert out["dbh_m"].iat[0] == (1 - w) * 0.30 + w * fitted["outline_dbh_m"].iat[0]
    assert "from one outline" in out["dbh_note"].iat[0]
    assert out["dbh_m"].iat[1] == 0.20 and out["dbh_note"].iat[1] == ""
    assert np.isnan(fits["outline_dbh_m"].iat[1])
    # a DBH so far from the cylinders alone (no width) is far less sure: the outline weighs more
    cyl_only, _ = blend_outline(trees, fits, fitted, np.array([tp.outline_ref_cylinders_sd_m]))
    w_cyl = tp.outline_ref_cylinders_sd_m**2 / (tp.outline_ref_cylinders_sd_m**2 + sd**2)
    assert w_cyl > w and np.isclose(cyl_only["dbh_m"].iat[0], (1 - w_cyl) * 0.30 + w_cyl * fitted["outline_dbh_m"].iat[0])
