"""Cylinder segments (spec 4, validation target 13.15) and end-to-end feature extraction."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest
from helpers.synthetic import Cylinder, Scene, Wall, forest_scene, grid, render, visible_length_m

from forestmap_assets.core.features.circle_models import CIRCLE_COLUMNS
from forestmap_assets.core.features.cylinders import (
    CYLINDER_COLUMNS,
    assemble_cylinders,
    cylinder_membership,
    extract_features,
)
from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.params import CylinderParams


def _circles(centres, normals, radii, chain=0, valid=None):
    """A final-iteration circle table from arrays."""
    c = np.asarray(centres, float)
    n = np.asarray(normals, float)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    k = len(c)
    return pd.DataFrame({
        "iteration": 2, "segment_id": np.arange(k), "row": np.arange(k)[::-1],
        "chain_id": np.broadcast_to(chain, k), "cx": c[:, 0], "cy": c[:, 1], "cz": c[:, 2],
        "radius_m": np.broadcast_to(radii, k).astype(float), "nx": n[:, 0], "ny": n[:, 1],
        "nz": n[:, 2], "n_points": 100, "n_inliers": 100, "mean_residual_m": 0.0,
        "rms_residual_m": 0.01, "valid": True if valid is None else valid, "reject_reason": "",
    }).astype(CIRCLE_COLUMNS)


def _straight(z0, z1, step=0.02, axis=(0, 0, 1), base=(5, 0, 0)):
    t = np.arange(0, (z1 - z0) / step + 0.5) * step
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    c = np.asarray(base, float) + (z0 + t)[:, None] * a
    return c, np.tile(a, (t.size, 1))


def test_straight_chain_gives_one_cylinder_with_mean_radius_and_cone_ends():
    c, n = _straight(0.0, 2.0, axis=(0.1, 0.0, 1.0))
    r = np.linspace(0.20, 0.16, len(c))  # tapering: truncated cone
    cyl = assemble_cylinders(_circles(c, n, r))
    assert len(cyl) == 1
    row = cyl.iloc[0]
    np.testing.assert_allclose(row[["x0", "y0", "z0"]].to_numpy(float), c[0], atol=1e-9)
    np.testing.assert_allclose(row[["x1", "y1", "z1"]].to_numpy(float), c[-1], atol=1e-9)
    assert row["length_m"] == pytest.approx(np.linalg.norm(c[-1] - c[0]))
    assert row["radius_m"] == pytest.approx(r.mean())
    assert row["r0_m"] == pytest.approx(0.20) and row["r1_m"] == pytest.approx(0.16)
    assert row["n_circles"] == len(c)
    assert row["tilt_deg"] == pytest.approx(np.degrees(np.arctan(0.1)))
    assert dict(cyl.dtypes.astype(str)) == CYLINDER_COLUMNS


def test_bend_of_15_degrees_splits_at_the_breaking_circle():
    lower, nl = _straight(0.0, 1.0)
    tilt = np.radians(15)
    d = np.array([np.sin(tilt), 0, np.cos(tilt)])
    upper = lower[-1] + np.arange(1, 51)[:, None] * 0.02 * d
    c = np.vstack([lower, upper])
    n = np.vstack([nl, np.tile(d, (50, 1))])
    cyl = assemble_cylinders(_circles(c, n, 0.1), CylinderParams(curvature_deg=12.0))
    assert len(cyl) == 2
    assert sorted(cyl["n_circles"]) == [50, len(lower)]
    # a sharp bend is found at the same circle against the running mean normal (inferred
    # alternative) ...
    run = assemble_cylinders(_circles(c, n, 0.1), CylinderParams(curvature_deg=12.0),
                             reference="running")
    assert sorted(run["n_circles"]) == [50, len(lower)]
    # ... but a gradual curve (normal turning 0 -> 36 deg) lags behind it: fewer, longer pieces
    ang = np.radians(np.linspace(0, 36, 121))
    dirs = np.stack([np.sin(ang), np.zeros_like(ang), np.cos(ang)], 1)
    arc = np.cumsum(0.02 * dirs, axis=0)
    first = assemble_cylinders(_circles(arc, dirs, 0.1))
    running = assemble_cylinders(_circles(arc, dirs, 0.1), reference="running")
    assert len(first) == 3 and len(running) == 2
    # a 10 deg bend stays one cylinder
    d10 = np.array([np.sin(np.radians(10)), 0, np.cos(np.radians(10))])
    c10 = np.vstack([lower, lower[-1] + np.arange(1, 51)[:, None] * 0.02 * d10])
    n10 = np.vstack([nl, np.tile(d10, (50, 1))])
    assert len(assemble_cylinders(_circles(c10, n10, 0.1))) == 1


@pytest.mark.parametrize("gap, pieces", [(0.2, 1), (0.3, 2)])
def test_gap_along_the_axis(gap, pieces):
    lower, nl = _straight(0.0, 1.0)
    upper, nu = _straight(1.0 + gap, 2.0 + gap)
    cyl = assemble_cylinders(_circles(np.vstack([lower, upper]), np.vstack([nl, nu]), 0.1))
    assert len(cyl) == pieces


def test_centre_line_must_follow_the_circle_normals():
    """(inferred) A chain whose centres climb at 45 deg while its circles were fitted
    perpendicular to a 30 deg-clamped normal (an oblique branch) is no cylinder; a leaning stem
    whose normals follow its centre line is kept, and the check can be switched off."""
    c, _ = _straight(0.0, 1.0, axis=(1.0, 0.0, 1.0))  # centres along a 45 deg line
    tilt30 = np.tile([np.sin(np.radians(30)), 0.0, np.cos(np.radians(30))], (len(c), 1))
    branch = _circles(c, tilt30, 0.05)
    assert assemble_cylinders(branch).empty  # 15 deg > curvature_deg (12)
    assert len(assemble_cylinders(branch, axis_normal_deg=20.0)) == 1
    assert len(assemble_cylinders(branch, axis_normal_deg=np.inf)) == 1
    c, n = _straight(0.0, 1.0, axis=(0.2, 0.1, 1.0))  # a leaning stem, normals = axis
    n = n + np.random.default_rng(0).normal(0, 0.02, n.shape)  # a few degrees of normal noise
    assert len(assemble_cylinders(_circles(c, n, 0.1))) == 1


def test_short_isolated_and_invalid_circles_make_no_cylinder():
    short, ns = _straight(0.0, 0.4)  # 0.4 m < 0.5 m forest minimum
    assert len(assemble_cylinders(_circles(short, ns, 0.1))) == 0
    assert len(assemble_cylinders(_circles(short, ns, 0.1),
                                  CylinderParams(min_length_m=0.3))) == 1
    leaves = np.array([[3, 1, 0.0], [4, -2, 0.5], [6, 3, 1.0]])  # scattered, same chain
    assert len(assemble_cylinders(_circles(leaves, np.tile([0, 0, 1.0], (3, 1)), 0.05))) == 0
    c, n = _straight(0.0, 2.0)
    assert len(assemble_cylinders(_circles(c, n, 0.1, valid=False))) == 0


def test_two_chains_and_membership():
    a, na = _straight(0.0, 1.5, base=(5, 0, 0))
    b, nb = _straight(0.0, 1.5, base=(5, 0.05, 0))  # same place, other chain: kept apart
    circ = pd.concat([_circles(a, na, 0.1, chain=3), _circles(b, nb, 0.1, chain=7)],
                     ignore_index=True)
    circ["segment_id"] = np.arange(len(circ))
    cyl, mapping = assemble_cylinders(circ, return_membership=True)
    assert sorted(cyl["chain_id"]) == [3, 7]
    assert len(mapping) == len(circ)
    assert mapping.groupby("cylinder_id").size().tolist() == [len(a), len(b)]
    member = cylinder_membership(circ)
    assert len(set(member[: len(a)])) == 1 and member[0] != member[-1]


# ---- end to end on analytic scenes ---------------------------------------------------------

def _match(cyl, stem):
    """Cylinders whose mid point lies within max(0.1, r) of ``stem``'s axis."""
    mid = (cyl[["x0", "y0", "z0"]].to_numpy() + cyl[["x1", "y1", "z1"]].to_numpy()) / 2
    w = mid - np.asarray(stem.base)
    a = np.asarray(stem.axis)
    perp = np.linalg.norm(w - (w @ a)[:, None] * a, axis=1)
    return cyl[perp < max(0.1, stem.radius)]


@pytest.fixture(scope="module")
def forest_window():
    """Full angular resolution (0.108 deg), 2.5 cm range noise, 12 stems of radius 0.05-0.3 m
    at 2-15 m leaning up to 10 deg, seen through a 100 deg x 50 deg window, plus branches."""
    scene = forest_scene(12, seed=11, r_min_m=2.0, r_max_m=15.0, azimuth_range_deg=(-45, 45),
                         min_separation_m=1.5)
    rng = np.random.default_rng(2)
    for s in scene.cylinders[:6]:  # thin branches (1.5-3 cm) just in front of some stems
        p = np.asarray(s.base) * (1 - 0.6 / np.hypot(*s.base[:2]))
        scene.cylinders.append(Cylinder((p[0], p[1], rng.uniform(0, 1)),
                                        tuple(rng.normal(size=3) / 3 + [0, 0, 1]),
                                        rng.uniform(0.008, 0.015), 1.5))
    a, e = grid((-50, 50), (-35, 15))
    img, _, label = render(scene, a, e, noise_m=0.025, seed=4, labels=True)
    visible = [visible_length_m(img, label, i) for i in range(12)]
    return img, scene.cylinders[:12], visible


def test_forest_every_stem_found_and_radius_rmse(forest_window):
    """Every stem with >= 1 m of visible trunk within 15 m becomes a cylinder; radius RMSE
    <= 1 cm with the along-beam refinement at full angular resolution and 2.5 cm noise."""
    img, stems, visible = forest_window
    targets = [s for s, v in zip(stems, visible, strict=True) if v >= 1.0]
    assert len(targets) >= 9  # two stems of this layout are hidden behind nearer ones
    res = {}
    for fit in ("linear", "ray"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            f = extract_features(img, fit=fit)
        cyl = f["cylinder_segments"]
        errs = []
        for s in targets:
            m = _match(cyl, s)
            assert len(m) > 0, (fit, s)
            assert m["length_m"].sum() > 1.0
            w = m["length_m"].to_numpy()
            errs.append(np.sum(w * (m["radius_m"].to_numpy() - s.radius) ** 2) / w.sum())
        res[fit] = np.sqrt(np.mean(errs))
        # every cylinder belongs to a stem (branches, ground: none)
        assert sum(len(_match(cyl, s)) for s in stems) == len(cyl)
    assert res["ray"] <= 0.01, res
    # the thesis' linear fit is biased low by 2-3 cm at 2.5 cm noise (documented, not hidden)
    assert 0.01 < res["linear"] < 0.04, res


def test_no_cylinders_on_walls_or_ground():
    a, e = grid((-60, 60), (-30, 20), step_deg=0.216)
    scene = Scene(walls=[Wall(6, -8, 6, 8), Wall(-3, 5, 6, 5), Wall(2, -4, 5, -7)])
    img, _ = render(scene, a, e, noise_m=0.025, seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        f = extract_features(img)
    assert len(f["cylinder_segments"]) == 0
    ground, _ = render(Scene(), a, e, noise_m=0.025, seed=2)
    g = extract_features(ground)
    assert all(len(t) == 0 for t in g.values())


def test_empty_and_no_return_images_give_well_formed_tables():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for img in (RangeImage(np.zeros((0, 0), np.float32), np.zeros(0), np.zeros(0)),
                    RangeImage(np.full((30, 40), np.nan, np.float32), np.arange(40) * 0.1,
                               -np.arange(30) * 0.1)):
            f = extract_features(img)
            assert set(f) == {"segments", "circle_models", "cylinder_segments"}
            assert all(len(t) == 0 for t in f.values())
            assert dict(f["cylinder_segments"].dtypes.astype(str)) == CYLINDER_COLUMNS
            assert dict(f["circle_models"].dtypes.astype(str)) == CIRCLE_COLUMNS


def test_chains_broken_by_lines_without_a_segment_are_walked_as_one():
    """A thin stem seen from afar: its chain breaks at every scan line without a segment, into
    pieces shorter than the minimum length. Linked end to end (gaps within max_gap_m, circles
    overlapping across) they give one cylinder; with ``link_chains`` off none. A chain beside the
    stem at the same heights, and one above it but 0.3 m aside, stay apart."""
    pieces = []
    for k, (z0, z1) in enumerate([(0.0, 0.36), (0.5, 0.86), (1.0, 1.36)]):  # 0.14 m gaps
        c, n = _straight(z0, z1, axis=(0.02, 0.0, 1.0), base=(15.0, 0.0, 0.0))
        pieces.append(_circles(c, n, 0.06, chain=10 + 7 * k))
    beside = _circles(*_straight(0.0, 1.36, base=(15.0, 0.5, 0.0)), 0.06, chain=3)  # its own stem
    aside = _circles(*_straight(1.5, 1.86, base=(15.3, 0.0, 0.0)), 0.06, chain=50)  # 0.3 m off the axis
    table = pd.concat([*pieces, beside, aside], ignore_index=True)
    table["segment_id"] = np.arange(len(table))
    cyl = assemble_cylinders(table, CylinderParams(min_length_m=0.5))
    stem = cyl[(cyl["y0"] < 0.25) & (cyl["x0"] < 15.2)]
    assert len(stem) == 1 and stem["n_circles"].iat[0] == sum(len(p) for p in pieces)
    assert stem["z0"].iat[0] == pytest.approx(0.0) and stem["z1"].iat[0] == pytest.approx(1.36, abs=0.03)
    assert ((cyl["y0"] > 0.25) & (cyl["n_circles"] == len(beside))).sum() == 1  # the neighbour stem, whole
    assert not (cyl["x0"] > 15.2).any()  # the piece 0.3 m aside: 0.36 m long, not linked
    off = assemble_cylinders(table, CylinderParams(min_length_m=0.5, link_chains=False))
    assert not ((off["y0"] < 0.25) & (off["x0"] < 15.2)).any()  # every piece too short alone
    # near a scanner: two pieces side by side continue one piece; no link is unambiguous
    near = [_circles(*_straight(0.0, 0.36, base=(2.0, 0.0, 0.0)), 0.1, chain=60),
            _circles(*_straight(0.5, 0.86, base=(2.0, 0.02, 0.0)), 0.1, chain=61),
            _circles(*_straight(0.5, 0.86, base=(2.0, -0.02, 0.0)), 0.1, chain=62)]
    cluttered = pd.concat(near, ignore_index=True)
    cluttered["segment_id"] = np.arange(len(cluttered))
    assert len(assemble_cylinders(cluttered, CylinderParams(min_length_m=0.5))) == 0
