"""Merging cylinder segments of several scans into trees with DBH (core/trees.py)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from forestmap_assets.core.geometry import compose, relative_pose, transform_points, wrap_deg
from forestmap_assets.core.mapping.cylinder_radii import axis_slopes
from forestmap_assets.core.mapping.trees import (
    absorb_nested,
    beam_options,
    cylinders_to_global,
    ground_under,
    merge_trees,
    nested_trees,
)


def _cyl(cid, base, lean, r0, r1, z0, z1, n=10):
    p0 = np.array(base) + np.array([*lean, 0]) * z0 + [0, 0, z0]
    p1 = np.array(base) + np.array([*lean, 0]) * z1 + [0, 0, z1]
    return dict(cylinder_id=cid, x0=p0[0], y0=p0[1], z0=p0[2], x1=p1[0], y1=p1[1], z1=p1[2],
                radius_m=(r0 + r1) / 2, r0_m=r0, r1_m=r1, n_circles=n, length_m=z1 - z0)


def test_a_tree_inside_another_stem_leaves_the_list():
    # a 30 cm stem of 20 cylinders, a one-cylinder 15 cm "tree" 8 cm from its axis (a fork's
    # limb continued down, a stub), two stems that touch (12 + 10 cm apart: both stay) and a
    # crown part without a DBH 5 cm from the second
    cyl = pd.DataFrame([_cyl(i, (0, 0, 0), (0.02, 0.0), 0.15, 0.15, 0.3 * i, 0.3 * i + 0.3) for i in range(4)]
                       + [_cyl(4, (0.08, 0, 0), (0.3, 0.0), 0.075, 0.075, 2.0, 2.9),
                          _cyl(5, (3, 0, 0), (0, 0), 0.12, 0.12, 0.5, 2.5), _cyl(6, (3.22, 0, 0), (0, 0), 0.1, 0.1, 0.5, 2.5),
                          _cyl(7, (3.05, 0, 0), (0, 0), 0.1, 0.1, 8.0, 9.0)])
    trees = pd.DataFrame({"tree_id": [1, 2, 3, 4, 5], "x": [0.0, 0.08, 3.0, 3.22, 3.05], "y": 0.0, "z": 0.0,
                          "dbh_m": [0.30, 0.15, 0.24, 0.20, np.nan], "n_scans": [5, 1, 3, 3, 1],
                          "n_cylinders": [20, 1, 6, 6, 1], "visible_length_m": 1.0, "dbh_note": ""})
    tree_of = np.array([1, 1, 1, 1, 2, 3, 4, 5])
    out, tree_of = absorb_nested(trees, tree_of)
    assert out["x"].tolist() == [0.0, 3.0, 3.22] and out["tree_id"].tolist() == [1, 2, 3]
    assert tree_of.tolist() == [1, 1, 1, 1, 0, 2, 3, 0]
    # the absorbed limb's lean (0.3) no longer tilts the stem's axis; its cylinder has no tree
    np.testing.assert_allclose(axis_slopes(cyl, tree_of, len(out)), [[0.02, 0.0], [0.0, 0.0], [0.0, 0.0]], atol=1e-12)
    kept, same = absorb_nested(trees.iloc[2:4].reset_index(drop=True), np.array([1, 2]))
    assert len(kept) == 2 and same.tolist() == [1, 2]


def test_a_tree_whose_axis_lies_on_a_thicker_ones_bark_leaves_the_list_once_measured():
    """With the DBH measured (tree_dbh), a tree within half its own radius plus 3 cm of a
    thicker one's bark overlaps it (a lobe's or stub's cylinder); the thicker stays whatever
    their cylinders' count, a tree 2 cm clear of the bark stays, and a stub without a DBH
    goes within 3 cm of the bark."""
    trees = pd.DataFrame({"tree_id": [1, 2, 3, 4, 5, 6], "x": [0.0, 0.31, 5.0, 5.37, 9.0, 9.27], "y": 0.0, "z": 0.0,
                          "dbh_m": [0.56, 0.11, 0.56, 0.14, 0.50, np.nan], "n_scans": 2,
                          "n_cylinders": [3, 5, 3, 1, 4, 1], "visible_length_m": 5.0, "dbh_note": ""})
    # 0.31 < 0.28 + 0.5 x 0.055 + 0.03; 0.37 > 0.28 + 0.5 x 0.07 + 0.03 (2 cm bark to bark); 0.27 < 0.25 + 0.03
    assert nested_trees(trees, 0.5, 0.03, prefer="thicker").tolist() == [False, True, False, False, False, True]
    # the cylinders' rule (inside the section, more cylinders first) keeps them all here
    assert not nested_trees(trees).any()


def test_understorey_below_the_top_height_is_not_a_tree():
    """A sapling whose one cylinder ends 1.9 m above the ground leaves the list with
    ``min_top_m`` 2.5, its cylinder belonging to no tree; the stem reaching 4 m stays, and so
    does a 14 cm stem that three scans saw up to a fork at 2.3 m."""
    grid = SimpleNamespace(z=np.zeros((150, 150)), x0=-5.0, y0=-5.0, cell_m=0.1)
    cyl = pd.DataFrame([_cyl(0, (0, 0, 0), (0, 0), 0.15, 0.15, 0.5, 2.0), _cyl(1, (0, 0, 0), (0, 0), 0.15, 0.15, 2.0, 4.0),
                        _cyl(2, (3, 1, 0), (0, 0), 0.04, 0.04, 0.4, 1.9)]
                       + [_cyl(3 + i, (6, 0, 0), (0, 0), 0.07, 0.07, 0.5, 2.3) for i in range(3)])
    cyl = cyl.assign(scan=["A", "A", "A", "A", "B", "C"])
    every, tree_of = merge_trees(cyl, grid)
    assert len(every) == 3 and tree_of.tolist() == [1, 1, 2, 3, 3, 3]
    trees, tree_of = merge_trees(cyl, grid, min_top_m=2.5)
    assert trees["x"].round(6).tolist() == [0.0, 6.0] and tree_of.tolist() == [1, 1, 0, 2, 2, 2]
    two, _ = merge_trees(cyl.assign(scan=["A", "A", "A", "A", "B", "B"]), grid, min_top_m=2.5)
    assert two["x"].round(6).tolist() == [0.0]


def test_the_stem_below_a_fork_stays_and_its_limb_leaves():
    """A 25 cm stem that four scans saw across breast height, forked at 2.4 m: the limb's five
    cylinders (18 cm, leaning 0.3, from 2.6 m up) continued down reach breast height 5 cm from
    the stem's axis. The stem seen there stays, though the limb has more cylinders, and keeps
    its DBH; the limb's cylinders belong to no tree (own realistic seed 206: 9.9 cm read for a
    24.8 cm stem about the limb's axis)."""
    grid = SimpleNamespace(z=np.zeros((150, 150)), x0=-5.0, y0=-5.0, cell_m=0.1)
    stem = [_cyl(i, (0, 0, 0), (0, 0), 0.125, 0.125, 0.5 + 0.05 * i, 2.2) for i in range(4)]
    limb = [_cyl(4 + i, (0.05 - 0.3 * 1.3, 0, 0), (0.3, 0), 0.09, 0.09, 2.6 + i, 3.5 + i) for i in range(5)]
    cyl = pd.DataFrame(stem + limb).assign(scan=["R", "T", "N", "S", "R", "N", "Q", "O", "R"])
    trees, tree_of = merge_trees(cyl, grid)
    assert len(trees) == 1 and tree_of.tolist() == [1, 1, 1, 1, 0, 0, 0, 0, 0]
    assert trees["x"].iloc[0] == pytest.approx(0.0, abs=1e-9) and trees["dbh_m"].iloc[0] == pytest.approx(0.25)
    # seen by one scan only near breast height, the stem is no better than a stub: more cylinders win
    one, tree_of = merge_trees(cyl.assign(scan=["R"] * 4 + ["R", "N", "Q", "O", "R"]), grid)
    assert len(one) == 1 and tree_of.tolist() == [0, 0, 0, 0, 1, 1, 1, 1, 1]


def test_pose_helpers_round_trip():
    a, b = (1.0, 2.0, 0.5, 30.0), (-3.0, 4.0, 0.1, 170.0)
    rel = relative_pose(b, a)
    back = compose(a, rel)
    np.testing.assert_allclose(back[:3], b[:3], atol=1e-12)
    assert abs(wrap_deg(back[3] - b[3])) < 1e-9
    assert wrap_deg(-180.0) == 180.0 and wrap_deg(190.0) == -170.0
    p = transform_points(np.array([[1.0, 0, 0]]), (0, 0, 0, 90))
    np.testing.assert_allclose(p, [[0, 1, 0]], atol=1e-12)


def test_merge_trees_from_two_scans():
    # three stems on flat ground at z = 0.2; scan S sees them from a pose (5, 1, 0.1, 40 deg)
    ground = 0.2
    stems = [((0.0, 0.0, ground), (0.03, 0.0), 0.16, 0.14), ((3.0, 1.0, ground), (0.0, 0.02, ), 0.08, 0.07),
             ((-2.0, 4.0, ground), (0.0, 0.0), 0.25, 0.24)]
    t_rows, s_rows = [], []
    pose_s = (5.0, 1.0, 0.1, 40.0)
    for k, (base, lean, r0, r1) in enumerate(stems):
        lean = (*lean, 0.0)[:2]
        t_rows.append(_cyl(k, base, lean, r0 + 0.01 * (r1 - r0), r1, 0.5, 2.5))  # breast height inside
        glob = pd.DataFrame([_cyl(k, base, lean, r0, r1, 1.0, 3.0)])
        # express in S's frame: inverse of pose_s
        for end in ("0", "1"):
            pts = glob[[f"x{end}", f"y{end}", f"z{end}"]].to_numpy()
            local = (pts - np.array(pose_s[:3])) @ np.array(
                [[np.cos(np.radians(40)), -np.sin(np.radians(40)), 0], [np.sin(np.radians(40)), np.cos(np.radians(40)), 0], [0, 0, 1]])
            glob[[f"x{end}", f"y{end}", f"z{end}"]] = local
        s_rows.append(glob.iloc[0].to_dict())
    per_scan = {"T": pd.DataFrame(t_rows), "S": pd.DataFrame(s_rows)}
    cyl = cylinders_to_global(per_scan, {"T": (0, 0, 0, 0), "S": pose_s})
    assert len(cyl) == 6 and set(cyl["scan"]) == {"T", "S"}
    grid = SimpleNamespace(z=np.full((200, 200), ground), x0=-10.0, y0=-10.0, cell_m=0.1)
    trees, tree_of = merge_trees(cyl, grid)
    assert len(trees) == 3 and (trees["n_scans"] == 2).all() and (trees["n_cylinders"] == 2).all()
    trees = trees.sort_values("x").reset_index(drop=True)
    expected = sorted(stems, key=lambda s: s[0][0])
    for row, (base, lean, r0, r1) in zip(trees.itertuples(), expected, strict=True):
        lean = (*lean, 0.0)[:2]
        zb = 1.3 + ground
        assert abs(row.z - ground) < 1e-9
        assert np.hypot(row.x - (base[0] + lean[0] * (zb)), row.y - (base[1] + lean[1] * zb)) < 0.01
        assert abs(row.dbh_m - 2 * (r0 + (r1 - r0) * 0.4)) < 0.01
        assert abs(row.visible_length_m - 2.5) < 1e-6


def test_empty_inputs():
    cyl = cylinders_to_global({}, {})
    trees, labels = merge_trees(cyl)
    assert trees.empty and list(trees.columns)[:3] == ["tree_id", "x", "y"] and labels.size == 0


def test_cylinders_to_global_records_the_observation_range():
    per_scan = {"T": pd.DataFrame([_cyl(0, (3.0, 4.0, 0.0), (0.0, 0.0), 0.1, 0.1, 0.5, 2.5)])}
    cyl = cylinders_to_global(per_scan, {"T": (10.0, -2.0, 0.3, 75.0)})
    assert cyl["range_m"].iloc[0] == pytest.approx(5.0)
    assert "range_m" in cylinders_to_global({}, {}).columns


def test_ground_under_ignores_crown_hits_where_the_ground_was_not_seen():
    # flat ground at 0.2; in 70 % of the cells around the stem only crown hits at 4-8 m remain
    rng = np.random.default_rng(1)
    z = np.full((60, 60), 0.2) + rng.normal(0, 0.01, (60, 60))
    crown = rng.random((60, 60)) < 0.7
    z[crown] = rng.uniform(4.0, 8.0, crown.sum())
    xy, r = np.array([[3.0, 3.0]]), np.array([0.15])
    assert ground_under(xy, r, z, 0.0, 0.0, 0.1)[0] == pytest.approx(0.2, abs=0.03)
    plain = ground_under(xy, r, z, 0.0, 0.0, 0.1, low_quantile=0.0, band_m=np.inf)[0]
    assert plain > 3.0  # the plain median of the annulus is a crown height


def _one_stem_from(ranges_and_radii, n=50):
    """Cylinders of one vertical stem at (0, 0) seen from scans at the given ranges."""
    per_scan, poses = {}, {}
    for k, (rng_m, radius) in enumerate(ranges_and_radii):
        per_scan[f"S{k}"] = pd.DataFrame([_cyl(0, (rng_m, 0.0, 0.0), (0.0, 0.0), radius, radius,
                                               0.5, 2.5, n=n)])
        poses[f"S{k}"] = (-rng_m, 0.0, 0.0, 0.0)
    return cylinders_to_global(per_scan, poses)


def _scans_cylinders(seen):
    """One cylinder a scan of one vertical stem at (0, 0): {scan: (range, r0, r1, z0, z1, n)}."""
    per_scan = {sid: pd.DataFrame([_cyl(0, (rng, 0.0, 0.0), (0.0, 0.0), r0, r1, z0, z1, n=n)])
                for sid, (rng, r0, r1, z0, z1, n) in seen.items()}
    return cylinders_to_global(per_scan, {sid: (-v[0], 0.0, 0.0, 0.0) for sid, v in seen.items()})


def test_dbh_prefers_near_observations_and_weights_by_beam_footprint():
    grid = SimpleNamespace(z=np.zeros((100, 100)), x0=-5.0, y0=-5.0, cell_m=0.1)
    # near scans see r = 0.150, far scans (wide footprint, mixed pixels) r = 0.175
    cyl = _one_stem_from([(6.0, 0.150), (9.0, 0.150), (22.0, 0.175), (26.0, 0.175)])
    plain, _ = merge_trees(cyl, grid, range_weighting=False, dbh_max_range_m=None)
    assert plain["dbh_m"].iloc[0] == pytest.approx(2 * 0.1625)
    near_only, _ = merge_trees(cyl, grid)
    assert near_only["dbh_m"].iloc[0] == pytest.approx(0.30)
    weighted, _ = merge_trees(cyl, grid, dbh_max_range_m=None)
    w = 1 / (0.042 + 0.003 * np.array([6.0, 9.0, 22.0, 26.0])) ** 2
    expect = 2 * np.average([0.150, 0.150, 0.175, 0.175], weights=w)
    assert weighted["dbh_m"].iloc[0] == pytest.approx(expect)
    assert 0.30 < expect < 2 * 0.1625
    # only far observations: they are used rather than giving no DBH
    far, _ = merge_trees(_one_stem_from([(22.0, 0.175), (26.0, 0.175)]), grid)
    assert far["dbh_m"].iloc[0] == pytest.approx(0.35)


def test_dbh_weighted_median_ignores_one_occluded_cylinder():
    grid = SimpleNamespace(z=np.zeros((100, 100)), x0=-5.0, y0=-5.0, cell_m=0.1)
    cyl = _one_stem_from([(5.0, 0.16), (6.0, 0.16), (7.0, 0.16), (8.0, 0.09)])
    mean, _ = merge_trees(cyl, grid, small_share=None)
    med, _ = merge_trees(cyl, grid, dbh_statistic="median", small_share=None)
    assert med["dbh_m"].iloc[0] == pytest.approx(0.32)
    assert mean["dbh_m"].iloc[0] < 0.31
    # the default leaves out a cylinder below 0.7 of the weighted median: the mean is 0.32 too
    trimmed, _ = merge_trees(cyl, grid)
    assert trimmed["dbh_m"].iloc[0] == pytest.approx(0.32)
    # not with fewer than two left, nor one only a little small
    two, _ = merge_trees(_one_stem_from([(5.0, 0.16), (6.0, 0.09)]), grid)
    assert two["dbh_m"].iloc[0] < 0.31
    mild, _ = merge_trees(_one_stem_from([(5.0, 0.16), (6.0, 0.16), (7.0, 0.12)]), grid)
    assert mild["dbh_m"].iloc[0] < 0.315


def test_dbh_limits_a_noisy_cylinder_taper_and_reaches_a_near_cylinder_above():
    grid = SimpleNamespace(z=np.zeros((100, 100)), x0=-5.0, y0=-5.0, cell_m=0.1)
    # one cylinder 0.5-2.5 m, fitted r0 = 0.17 at the bottom, r1 = 0.11 at the top (3 cm/m):
    # the stem is r = 0.14 at mid height; at breast height (1.3 m) the fitted cone says 0.146
    cyl = cylinders_to_global({"A": pd.DataFrame([_cyl(0, (8.0, 0.0, 0.0), (0.0, 0.0), 0.17,
                                                       0.11, 0.5, 2.5)])},
                              {"A": (-8.0, 0.0, 0.0, 0.0)})
    cone, _ = merge_trees(cyl, grid, max_taper_m_per_m=None)
    assert cone["dbh_m"].iloc[0] == pytest.approx(2 * (0.17 - 0.03 * 0.8))
    limited, _ = merge_trees(cyl, grid)  # slope limited to 1 cm/m about mid height (1.5 m)
    assert limited["dbh_m"].iloc[0] == pytest.approx(2 * (0.14 + 0.01 * 0.2))
    # a near scan's cylinder starting 0.8 m above breast height joins a far scan's at 1.3 m
    near = _cyl(0, (6.0, 0.0, 0.0), (0.0, 0.0), 0.14, 0.14, 2.1, 4.0)
    far = _cyl(0, (18.0, 0.0, 0.0), (0.0, 0.0), 0.17, 0.17, 0.5, 2.0)
    both = cylinders_to_global({"N": pd.DataFrame([near]), "F": pd.DataFrame([far])},
                               {"N": (-6.0, 0.0, 0.0, 0.0), "F": (-18.0, 0.0, 0.0, 0.0)})
    old, _ = merge_trees(both, grid, dbh_reach_m=0.6)
    assert old["dbh_m"].iloc[0] == pytest.approx(0.34)  # the far cylinder alone
    new, _ = merge_trees(both, grid)
    w = np.array([50, 50]) / (0.042 + 0.003 * np.array([6.0, 18.0])) ** 2
    assert new["dbh_m"].iloc[0] == pytest.approx(2 * np.average([0.14, 0.17], weights=w))


def test_a_lone_near_cylinder_far_too_small_gives_way_to_agreeing_ones():
    """One scan sees a 32 cm stem's partial arc near breast height from 17 m (r 6 cm); three
    scans beyond 20 m agree on r 17 cm: the lone cylinder no longer decides (dbh_note says so).
    Two others of two scans that disagree with each other still decide when both read 1.4 times
    its radius or more (own realistic seed 49); one of them under that, or both agreeing on a
    smaller radius, leave it alone."""
    grid = SimpleNamespace(z=np.zeros((100, 100)), x0=-5.0, y0=-5.0, cell_m=0.1)
    cyl = _one_stem_from([(17.0, 0.063), (22.9, 0.170), (25.4, 0.170), (25.5, 0.177)])
    trees, _ = merge_trees(cyl, grid)
    w = 50 / (0.042 + 0.003 * np.array([22.9, 25.4, 25.5])) ** 2
    assert trees["dbh_m"].iloc[0] == pytest.approx(2 * np.average([0.170, 0.170, 0.177], weights=w))
    assert "the one nearest gave 12.6 cm" in trees["dbh_note"].iloc[0]
    old, _ = merge_trees(cyl, grid, lone_ratio=None, lone_one_scan_ratio=None)
    assert old["dbh_m"].iloc[0] == pytest.approx(0.126)
    split, _ = merge_trees(_one_stem_from([(17.0, 0.063), (22.9, 0.10), (25.4, 0.17)]), grid)
    assert 0.2 <= split["dbh_m"].iloc[0] <= 0.34
    assert "the one nearest gave 12.6 cm" in split["dbh_note"].iloc[0]
    mixed, _ = merge_trees(_one_stem_from([(17.0, 0.063), (22.9, 0.08), (25.4, 0.17)]), grid)
    assert mixed["dbh_m"].iloc[0] == pytest.approx(0.126)
    thin, _ = merge_trees(_one_stem_from([(17.0, 0.063), (22.9, 0.08), (25.4, 0.08)]), grid)
    assert thin["dbh_m"].iloc[0] == pytest.approx(0.126)


def test_the_cylinders_of_one_scan_too_small_give_way_like_a_lone_one():
    """Own realistic seed 16: a 44 cm stem read 12.8 cm from two cylinders of one scan 17 m
    away (a stub on the stem), where scans beyond 20 m read larger radii. One scan's cylinders
    are one observation: they give way as a lone cylinder does. Others that agree within 30 %
    (not 20 %) of their median still decide."""
    grid = SimpleNamespace(z=np.zeros((100, 100)), x0=-5.0, y0=-5.0, cell_m=0.1)
    near = pd.DataFrame([_cyl(0, (17.0, 0.0, 0.0), (0.0, 0.0), 0.063, 0.063, 0.5, 1.2, n=50),
                         _cyl(1, (17.0, 0.0, 0.0), (0.0, 0.0), 0.057, 0.057, 1.2, 2.5, n=50)])
    per_scan, poses = {"S0": near}, {"S0": (-17.0, 0.0, 0.0, 0.0)}
    for k, (rng_m, radius, n) in enumerate([(22.5, 0.112, 150), (23.8, 0.139, 50), (28.6, 0.141, 50)], start=1):
        per_scan[f"S{k}"] = pd.DataFrame([_cyl(0, (rng_m, 0.0, 0.0), (0.0, 0.0), radius, radius, 0.5, 2.5, n=n)])
        poses[f"S{k}"] = (-rng_m, 0.0, 0.0, 0.0)
    cyl = cylinders_to_global(per_scan, poses)
    trees, _ = merge_trees(cyl, grid)
    w = np.array([150, 50, 50]) / (0.042 + 0.003 * np.array([22.5, 23.8, 28.6])) ** 2
    assert trees["dbh_m"].iloc[0] == pytest.approx(2 * np.average([0.112, 0.139, 0.141], weights=w))
    assert "cylinders within 2 m of breast height" in trees["dbh_note"].iloc[0]
    # 0.139 and 0.141 lie 24-26 % above 0.112, and 0.112 is under twice the near scan's radius
    strict, _ = merge_trees(cyl, grid, lone_agree=0.2, lone_ratio=2.0, lone_one_scan_ratio=None)
    assert strict["dbh_m"].iloc[0] == pytest.approx(0.12)  # the near scan's two cylinders decide


def test_one_other_scan_far_thicker_gives_the_dbh():
    """Held-out own realistic seed 72: a 22 cm stem read 11.6 cm from one scan's cylinder 16 m
    away (understorey hid the stem at breast height), where the one other scan near breast
    height, 23 m away, read 21.8 cm. It decides when it reads 1.6 times the radius or more."""
    grid = SimpleNamespace(z=np.zeros((100, 100)), x0=-5.0, y0=-5.0, cell_m=0.1)
    cyl = _scans_cylinders({"N": (15.8, 0.058, 0.058, 1.2, 1.7, 16), "T": (23.2, 0.109, 0.109, 2.7, 3.5, 20)})
    trees, _ = merge_trees(cyl, grid)
    assert trees["dbh_m"].iloc[0] == pytest.approx(0.218)
    assert "1 cylinders of other scans" in trees["dbh_note"].iloc[0]
    assert merge_trees(cyl, grid, lone_one_scan_ratio=None)[0]["dbh_m"].iloc[0] == pytest.approx(0.116)
    assert merge_trees(cyl, grid, lone_one_scan_ratio=2.0)[0]["dbh_m"].iloc[0] == pytest.approx(0.116)
    # the other scan's cylinder 2.3 m above breast height: within the rule's 2.5 m, not 2.0 m
    high = _scans_cylinders({"N": (15.8, 0.058, 0.058, 1.2, 1.7, 16), "T": (23.2, 0.109, 0.109, 3.6, 4.4, 20)})
    assert merge_trees(high, grid)[0]["dbh_m"].iloc[0] == pytest.approx(0.218)
    assert merge_trees(high, grid, lone_one_scan_reach_m=2.0)[0]["dbh_m"].iloc[0] == pytest.approx(0.116)


def test_near_scans_just_beyond_reach_outrank_far_ones_at_breast_height():
    """Held-out seed 67: a 32 cm stem read 22 cm from cylinders seen 26 m away spanning breast
    height, where a scan 13 m away read 32 cm from 1.04 m above it. Within 1.5 m, near scans'
    cones (extrapolated) give the DBH when no near one reaches within 1 m."""
    grid = SimpleNamespace(z=np.zeros((100, 100)), x0=-5.0, y0=-5.0, cell_m=0.1)
    cyl = _scans_cylinders({"R": (25.6, 0.109, 0.063, 0.2, 3.1, 51), "N": (12.7, 0.159, 0.157, 2.34, 3.4, 47)})
    trees, _ = merge_trees(cyl, grid)
    slope = (0.157 - 0.159) / (3.4 - 2.34)  # the stem thickening downwards, within 1 cm/m
    assert trees["dbh_m"].iloc[0] == pytest.approx(2 * (0.158 + slope * (1.3 - 2.87)))
    assert trees["dbh_note"].iloc[0].startswith("the cylinders within 1 m of breast height seen only from 26 m")
    alone = {"lone_one_scan_ratio": None}  # which would also let the near scan decide here
    far, _ = merge_trees(cyl, grid, dbh_close_reach_m=None, **alone)
    assert far["dbh_m"].iloc[0] < 0.2  # the far cylinder's tapering cone
    beyond, _ = merge_trees(cyl, grid, dbh_close_reach_m=1.0, **alone)
    assert beyond["dbh_m"].iloc[0] == pytest.approx(far["dbh_m"].iloc[0])


def test_a_near_scans_heavy_small_cylinders_do_not_set_the_median_alone():
    """Own realistic seed 22: a 20 cm stem read 11 cm because a scan 7 m away saw a thin object
    on its side (two cylinders, r 4 cm, many circles, small footprints) and outweighed two
    scans that read r 9.5 cm. The small-cylinder rule's median is one vote a scan."""
    grid = SimpleNamespace(z=np.zeros((100, 100)), x0=-5.0, y0=-5.0, cell_m=0.1)
    per_scan = {"S0": pd.DataFrame([_cyl(0, (7.0, 0.0, 0.0), (0.0, 0.0), 0.037, 0.037, 0.3, 1.0, n=130),
                                    _cyl(1, (7.0, 0.0, 0.0), (0.0, 0.0), 0.045, 0.045, 1.0, 2.5, n=130)]),
                "S1": pd.DataFrame([_cyl(0, (12.0, 0.0, 0.0), (0.0, 0.0), 0.096, 0.096, 0.3, 2.0, n=43)]),
                "S2": pd.DataFrame([_cyl(0, (14.0, 0.0, 0.0), (0.0, 0.0), 0.093, 0.093, 0.3, 2.0, n=58)])}
    poses = {"S0": (-7.0, 0.0, 0.0, 0.0), "S1": (-12.0, 0.0, 0.0, 0.0), "S2": (-14.0, 0.0, 0.0, 0.0)}
    trees, _ = merge_trees(cylinders_to_global(per_scan, poses), grid)
    w = np.array([43, 58]) / (0.042 + 0.003 * np.array([12.0, 14.0])) ** 2
    assert trees["dbh_m"].iloc[0] == pytest.approx(2 * np.average([0.096, 0.093], weights=w))


def _seed132_stem(t_radius=(0.185, 0.168), with_t=True):
    """Own realistic seed 132's 35.4 cm stem: scan Q 11 m away saw a 6 cm arc from 1.5 m up,
    scan R 17 m away the flared butt (0.1-0.8 m) and the stem above 3 m, scan T 26 m away the
    stem from 2 m up. {scan: [(z0, z1, r0, r1, n_circles)]} above a flat ground."""
    seen = {"Q": (11.05, [(1.54, 2.89, 0.0575, 0.068, 62)]),
            "R": (16.8, [(0.13, 0.82, 0.198, 0.199, 26), (3.10, 5.12, 0.168, 0.171, 59)])}
    if with_t:
        seen["T"] = (25.8, [(2.03, 3.24, *t_radius, 25)])
    per_scan = {sid: pd.DataFrame([_cyl(i, (rng, 0.0, 0.0), (0.0, 0.0), r0, r1, z0, z1, n=n)
                                   for i, (z0, z1, r0, r1, n) in enumerate(cyls)])
                for sid, (rng, cyls) in seen.items()}
    return cylinders_to_global(per_scan, {sid: (-v[0], 0.0, 0.0, 0.0) for sid, v in seen.items()})


def test_of_two_scans_near_breast_height_a_partial_arc_gives_way():
    """Two cylinders of two scans near breast height, r 6 cm and 20 cm: the one under 0.7 of
    the median over three or more scans within 2 m (cones continued) is left out. Where the
    third scan also reads small, or no third scan is there, both stay."""
    grid = SimpleNamespace(z=np.zeros((100, 100)), x0=-5.0, y0=-5.0, cell_m=0.1)
    trees, _ = merge_trees(_seed132_stem(), grid)
    assert trees["dbh_m"].iloc[0] == pytest.approx(0.397, abs=0.002)  # the butt cylinder's end
    both = merge_trees(_seed132_stem(), grid, small_share=None)[0]["dbh_m"].iloc[0]
    assert both < 0.2
    assert merge_trees(_seed132_stem(t_radius=(0.07, 0.07)), grid)[0]["dbh_m"].iloc[0] == pytest.approx(both)
    assert merge_trees(_seed132_stem(with_t=False), grid)[0]["dbh_m"].iloc[0] == pytest.approx(both)


def test_a_narrow_beam_lets_far_cylinders_give_the_dbh():
    """Sylva 41: a 48.6 cm stem read 41.4 cm from the one cylinder within 20 m, where four from
    19-30 m read 46-50 cm. The near rule's 20 m holds for the own simulator's 42 mm + 3 mrad
    beam; a survey-grade beam (5 mm + 0.3 mrad) does not widen far stems, so all take part."""
    own = beam_options(0.042, 0.003)
    assert own["dbh_max_range_m"] == pytest.approx(20.0)
    grid = SimpleNamespace(z=np.zeros((100, 100)), x0=-5.0, y0=-5.0, cell_m=0.1)
    cyl = _one_stem_from([(15.7, 0.207), (19.1, 0.23), (21.8, 0.245), (28.0, 0.245), (29.8, 0.24)])
    near, _ = merge_trees(cyl, grid, **own)
    assert near["dbh_m"].iloc[0] == pytest.approx(2 * np.average(
        [0.207, 0.23], weights=1 / (0.042 + 0.003 * np.array([15.7, 19.1])) ** 2))
    narrow = beam_options(0.005, 0.0003)
    assert narrow["dbh_max_range_m"] > 300
    far, _ = merge_trees(cyl, grid, **narrow)
    w = 1 / (0.005 + 0.0003 * np.array([15.7, 19.1, 21.8, 28.0, 29.8])) ** 2
    assert far["dbh_m"].iloc[0] == pytest.approx(2 * np.average([0.207, 0.23, 0.245, 0.245, 0.24], weights=w))

