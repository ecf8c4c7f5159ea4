"""Issue 18: every tree of the tree list has a DBH or a reason in ``dbh_note`` (core/mapping/trees.py)."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from forestmap_assets.core.mapping.trees import TREE_COLUMNS, merge_trees
from forestmap_assets.outputs.exports import TREE_COLUMNS as CSV_COLUMNS
from forestmap_assets.outputs.exports import write_geojson

GROUND = 0.2
FLAT = SimpleNamespace(z=np.full((100, 100), GROUND), x0=-5.0, y0=-5.0, cell_m=0.1)


def _cyl(x, r0, r1, z0, z1, *, scan="A", range_m=8.0, n=40):
    """One vertical cylinder at (x, 0) from ``z0`` to ``z1`` above the ground (global frame)."""
    return dict(scan=scan, cylinder_id=0, x0=x, y0=0.0, z0=GROUND + z0, x1=x, y1=0.0,
                z1=GROUND + z1, radius_m=(r0 + r1) / 2, r0_m=r0, r1_m=r1, n_circles=n,
                range_m=range_m)


def _one_tree(*cylinders, grid=FLAT):
    trees, _ = merge_trees(pd.DataFrame(list(cylinders)), grid)
    assert len(trees) == 1 and list(trees.columns) == TREE_COLUMNS
    return trees.iloc[0]


def test_normal_tree_has_no_note():
    tree = _one_tree(_cyl(0.0, 0.15, 0.15, 0.5, 2.5), _cyl(0.0, 0.15, 0.15, 0.8, 3.0, scan="B"))
    assert tree["dbh_m"] == pytest.approx(0.30)
    assert tree["dbh_note"] == ""


def test_near_cylinder_end_keeps_its_dbh_and_says_so():
    # starts 0.5 m above breast height: within dbh_reach_m, the radius at its lower end
    tree = _one_tree(_cyl(0.0, 0.15, 0.15, 1.8, 3.5))
    assert tree["dbh_m"] == pytest.approx(0.30)
    assert tree["dbh_note"] == (
        "no cylinder at breast height: radius at the nearest end of 1 cylinder starting 1.8 m "
        "above the ground (0.5 m above breast height)")


def test_stem_seen_only_above_reach_gets_an_extrapolated_dbh():
    # 2.5-4.5 m above the ground: 1.2 m above breast height, beyond dbh_reach_m = 1.0 but
    # within dbh_extrapolate_m = 2.0; fitted taper 0.5 cm/m continued down to 1.3 m
    tree = _one_tree(_cyl(0.0, 0.150, 0.140, 2.5, 4.5))
    assert tree["dbh_m"] == pytest.approx(2 * (0.145 + 0.005 * (3.5 - 1.3)))
    assert tree["dbh_note"] == (
        "no cylinder within 1 m of breast height: taper extrapolated 1.2 m down from 1 cylinder "
        "starting 2.5 m above the ground")
    assert abs(tree["x"]) < 1e-9 and tree["z"] == pytest.approx(GROUND)


def test_extrapolated_taper_is_limited_to_a_plausible_stem():
    # a fitted slope widening upwards is taken as no taper; a steep one as 1 cm/m of radius
    widening = _one_tree(_cyl(0.0, 0.12, 0.16, 3.0, 4.0))
    assert widening["dbh_m"] == pytest.approx(0.28)
    steep = _one_tree(_cyl(0.0, 0.20, 0.14, 3.0, 4.0))
    assert steep["dbh_m"] == pytest.approx(2 * (0.17 + 0.01 * (3.5 - 1.3)))
    assert "extrapolated 1.7 m down" in steep["dbh_note"]


def test_far_cylinder_is_noted():
    tree = _one_tree(_cyl(0.0, 0.15, 0.15, 2.8, 4.0, range_m=24.0))
    assert tree["dbh_m"] == pytest.approx(0.30)
    assert tree["dbh_note"].endswith(", seen from 24 m or farther")


def test_no_usable_cylinder_leaves_dbh_empty_with_the_reason():
    # a crown part 6-7 m up that no stem below was merged with
    tree = _one_tree(_cyl(0.0, 0.10, 0.09, 6.0, 7.0))
    assert np.isnan(tree["dbh_m"])
    assert tree["dbh_note"] == (
        "no DBH: no cylinder within 2 m of breast height (the lowest starts 6.0 m above the "
        "ground)")
    # a wider extrapolation limit reaches it
    trees, _ = merge_trees(pd.DataFrame([_cyl(0.0, 0.10, 0.09, 6.0, 7.0)]), FLAT,
                           dbh_extrapolate_m=5.0)
    assert trees["dbh_m"].iloc[0] == pytest.approx(2 * (0.095 + 0.01 * (6.5 - 1.3)))


def test_unseen_ground_is_noted():
    tree = _one_tree(_cyl(0.0, 0.15, 0.15, 0.5, 2.5), grid=None)
    assert tree["dbh_m"] == pytest.approx(0.30)
    assert tree["z"] == pytest.approx(GROUND + 0.5)
    assert tree["dbh_note"] == ("ground under the stem not seen: breast height taken 1.3 m above "
                                "the lowest cylinder end")


def test_every_tree_has_a_dbh_or_a_note_and_geojson_carries_it(tmp_path):
    cyl = pd.DataFrame([
        _cyl(0.0, 0.15, 0.15, 0.5, 2.5),  # normal
        _cyl(3.0, 0.150, 0.140, 2.5, 4.5),  # extrapolated
        _cyl(-3.0, 0.10, 0.09, 6.0, 7.0),  # none
    ])
    trees, _ = merge_trees(cyl, FLAT)
    trees = trees.sort_values("x").reset_index(drop=True)
    assert (trees["dbh_m"].notna() | (trees["dbh_note"] != "")).all()
    assert [bool(n) for n in trees["dbh_note"]] == [True, False, True]
    campaign = SimpleNamespace(name="t18", scan_ids=["A"])
    doc = json.loads(write_geojson(trees, tmp_path / "trees.geojson", campaign).read_text())
    props = [f["properties"] for f in doc["features"]]
    assert [p["dbh_note"] for p in props] == list(trees["dbh_note"])
    assert props[0]["dbh_m"] is None and props[0]["dbh_note"].startswith("no DBH")
    assert "dbh_note" not in CSV_COLUMNS  # trees.csv keeps the header of the design contract


def test_ground_seen_above_the_stem_is_bounded_by_its_lowest_cylinder():
    """Every cell around the stem holds a crown hit 4.9 m up (the ground was never seen there):
    breast height is taken 1.3 m above the lowest cylinder end, not 1.3 m above the crown, where
    the stem is thinner (a rendered survey's 47 cm stem read 35.7 cm)."""
    crown = SimpleNamespace(z=np.full((100, 100), GROUND + 4.9), x0=-5.0, y0=-5.0, cell_m=0.1)
    stem = (_cyl(0.0, 0.24, 0.20, 0.2, 5.0), _cyl(0.0, 0.17, 0.15, 5.2, 8.0, scan="B"))
    tree = _one_tree(*stem, grid=crown)
    assert tree["z"] == pytest.approx(GROUND + 0.2)
    assert tree["dbh_m"] == pytest.approx(2 * (0.24 - 0.04 * 1.3 / 4.8), abs=1e-3)
    assert "seen 4.7 m above its lowest cylinder" in tree["dbh_note"]
    assert _one_tree(*stem)["z"] == pytest.approx(GROUND)  # the ground seen below the stem stays
