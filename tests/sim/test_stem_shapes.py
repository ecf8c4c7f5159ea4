"""Realistic stems of the virtual forest (issue 19, ``sim/stem_shapes.py``): shapes, truth, mesh
resolution, occlusion by understorey and stubs. Small plots at quarter resolution."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from forestmap_assets.sim import make_forest, simulate_campaign
from forestmap_assets.sim.evaluate import scan_stems
from forestmap_assets.sim.scene_mesh import KIND_BRANCH, KIND_STEM, KIND_UNDERSTOREY
from forestmap_assets.sim.stem_shapes import (
    SHAPE_COLUMNS,
    girth_diameter,
    ring_heights,
    section_radius,
    stem_surface,
    surface_offset,
)
from forestmap_assets.sim.stems import STEM_COLUMNS, breast_height_table, stems_in_frame

SMALL = dict(scans=3, trees=20, plot_size=30.0, seed=3, resolution="quarter")
PSI = np.linspace(0, 2 * np.pi, 720, endpoint=False)


@pytest.fixture(scope="module")
def forests():
    return (make_forest(40, 40.0, n_scans=6, seed=1),
            make_forest(40, 40.0, n_scans=6, seed=1, stems="realistic"))


@pytest.fixture(scope="module")
def campaigns(tmp_path_factory):
    root = tmp_path_factory.mktemp("shapes")
    return (simulate_campaign(root / "circ", **SMALL),
            simulate_campaign(root / "real", **SMALL, stems="realistic",
                              scanner_kwargs={"range_sigma_m": 0.0}))


def test_realistic_forest_shares_the_plot_and_draws_the_shapes(forests):
    circ, real = forests
    base = ["x_base", "y_base", "z_base", "lean_x", "lean_y", "r_base_m", "taper_m_per_m",
            "height_m", "crown_base_m"]
    pd.testing.assert_frame_equal(circ.stems[base], real.stems[base])
    assert np.array_equal(circ.scan_xy, real.scan_xy)
    st = real.stems
    assert list(st.columns) == STEM_COLUMNS + SHAPE_COLUMNS
    assert st["flattening"].between(0.05, 0.15).all()
    assert st["flare_height_m"].between(0.5, 1.0).all() and st["n_lobes"].between(3, 6).all()
    assert st["bark_m"].between(0.005, 0.020).all() and st["sweep_m"].between(0.01, 0.08).all()
    lean = np.degrees(np.arctan(np.hypot(st["lean_x"], st["lean_y"])))
    assert lean.max() <= 8.0 + 1e-9
    fork = st["fork_h_m"].notna()
    assert 2 <= fork.sum() <= 20 and st.loc[fork, "fork_h_m"].between(2, 8).all()
    assert (st.loc[fork, "fork_r_m"] < st.loc[fork, "r_base_m"]).all()
    # dead branches low on the trunks (the crowns start at 3 m or higher)
    for f, lo in ((circ, 0), (real, 20)):
        m = f.mesh
        c = m.vertices[m.triangles[m.kind == KIND_BRANCH]].mean(1)
        above = c[:, 2] - f.ground.height(c[:, 0], c[:, 1])
        n_low = len(np.unique(m.part[m.kind == KIND_BRANCH][(above > 0.8) & (above < 2.5)]))
        assert n_low >= lo and (lo or n_low == 0)
    # a dense understorey: several times as many objects
    n_under = [len(np.unique(f.mesh.part[f.mesh.kind == KIND_UNDERSTOREY])) for f in forests]
    assert n_under[1] > 4 * n_under[0]
    again = make_forest(40, 40.0, n_scans=6, seed=1, stems="realistic")
    assert np.array_equal(again.mesh.vertices, real.mesh.vertices)
    assert again.stems.equals(real.stems)


def test_truth_dbh_is_the_mean_diameter_at_breast_height(forests):
    st = forests[1].stems
    truth = breast_height_table(st).set_index("tree_id")
    for _, row in st.iterrows():
        r = section_radius(row, 1.3, PSI)
        dbh = truth.loc[row["tree_id"], "dbh_m"]
        assert np.isclose(2 * r.mean(), dbh, rtol=1e-9)  # mean diameter through the centre
        d = r + np.roll(r, len(PSI) // 2)  # diameters through the centre
        assert np.isclose((d.max() + d.min()) / 2, dbh, rtol=1e-6)  # cross-calipering
        assert np.isclose(1 - d.min() / d.max(), row["flattening"], rtol=1e-3)
        assert dbh <= row["dbh_girth_m"] <= 1.01 * dbh
        assert np.isclose(girth_diameter(row), row["dbh_girth_m"])
        # flare and flutes: the mean radius grows near the ground, not from 1 m up
        r_lin = row["r_base_m"] - row["taper_m_per_m"] * np.array([0.0, 1.0])
        assert np.isclose(section_radius(row, 1.0, PSI).mean(), r_lin[1], rtol=1e-9)
        assert np.isclose(section_radius(row, 0.0, PSI).mean(), r_lin[0] + row["flare_m"],
                          rtol=1e-9)
    # x, y: the centre of the section at 1.3 m, with sweep (off the straight lean line)
    straight = st["x_base"] + 1.3 * st["lean_x"]
    assert (np.abs(truth["x"].to_numpy() - straight.to_numpy()) > 1e-4).mean() > 0.8


def test_mesh_follows_the_model_finely(forests):
    st = forests[1].stems
    row = st.loc[st["r_base_m"].idxmax()]
    (v, f), *_ = stem_surface(row, np.random.default_rng(0))
    h, psi, err = surface_offset(row, v)
    low = (h > 0.2) & (h < 6)
    assert abs(err[low].mean()) < 0.0015  # bark relief has zero mean
    assert 0.6 * row["bark_m"] / 2 < err[low].std() < 1.1 * row["bark_m"] / 2
    # vertices every few cm around and along the lower trunk
    hr = ring_heights(-0.3, row["height_m"])
    ring = v.reshape(len(hr), -1, 3)
    near = (hr > 0.0) & (hr < 4.0)
    around = np.linalg.norm(ring - np.roll(ring, 1, axis=1), axis=2)[near]
    along = np.linalg.norm(np.diff(ring, axis=0), axis=2)[near[:-1]]
    assert np.quantile(around, 0.99) < 0.04 and along.max() < 0.04
    # every stem of the forest: the mesh matches its own table (fork leaders excluded)
    m = forests[1].mesh
    for _, row in st.iloc[::7].iterrows():
        sel = (m.tree == row["tree_id"]) & (m.kind == KIND_STEM)
        main = sel & (m.part == m.part[sel].min())
        h, _, err = surface_offset(row, m.vertices[np.unique(m.triangles[main])])
        assert np.quantile(np.abs(err[h > 0]), 0.99) < 3 * row["bark_m"] / 2 + 0.002


def test_realistic_campaign_truth_and_stem_hits(campaigns):
    camp = campaigns[1]
    stems = pd.read_csv(camp / "truth" / "stems.csv")
    trees = pd.read_csv(camp / "truth" / "trees.csv")
    assert list(stems.columns) == STEM_COLUMNS + SHAPE_COLUMNS
    assert np.allclose(breast_height_table(stems)[["x", "y", "dbh_m"]], trees[["x", "y", "dbh_m"]],
                       atol=1e-5)
    poses = pd.read_csv(camp / "truth" / "poses.csv").set_index("scan")
    assert np.isfinite(scan_stems(camp, "S")[["ax", "ay", "az", "r_base_m"]]).all().all()
    # noise-free stem hits at breast height lie on the surface, within the bark relief
    errs = []
    for sid in ("T", "S", "R"):
        p = poses.loc[sid]
        st = stems_in_frame(stems, p[["x", "y", "z"]].to_numpy(float), float(p["heading_deg"]))
        st = st.set_index("tree_id")
        with np.load(camp / "scans" / f"{sid}.npz") as z:
            r, az, el = z["range"], np.radians(z["azimuth_deg"]), np.radians(z["elevation_deg"])
        with np.load(camp / "truth" / "labels" / f"{sid}.npz") as z:
            kind, tree, mixed = z["kind"], z["tree_id"], z["mixed"]
        xyz = np.stack([r * np.cos(el)[:, None] * np.cos(az)[None],
                        r * np.cos(el)[:, None] * np.sin(az)[None],
                        r * np.sin(el)[:, None] * np.ones_like(az)[None]], axis=-1)
        sel = (kind == KIND_STEM) & ~mixed & np.isfinite(r)
        for tid in np.unique(tree[sel]):
            row = st.loc[tid].copy()
            row["tree_id"] = tid
            h, _, e = surface_offset(row, xyz[sel & (tree == tid)])
            bh = (h > 1.0) & (h < 1.6) & (e < 0.1)  # not on a fork leader
            errs.append(pd.DataFrame({"err": e[bh], "sd": row["bark_m"] / 2}))
    e = pd.concat(errs)
    assert len(e) > 150
    assert abs(e["err"].median()) < 0.003
    assert np.quantile(np.abs(e["err"] / e["sd"]), 0.95) < 3.0


def _breast_height_views(camp, max_d: float = 15.0) -> np.ndarray:
    """Share of the central breast-height silhouette (1.0-1.6 m, 80 % of the width) of each
    true stem within ``max_d`` of each scan whose pixels hit that stem."""
    poses = pd.read_csv(camp / "truth" / "poses.csv").set_index("scan")
    stems = pd.read_csv(camp / "truth" / "stems.csv")
    out = []
    for sid, p in poses.iterrows():
        st = stems_in_frame(stems, p[["x", "y", "z"]].to_numpy(float), float(p["heading_deg"]))
        bh = breast_height_table(st)
        with np.load(camp / "scans" / f"{sid}.npz") as z:
            az, el = z["azimuth_deg"], z["elevation_deg"]
        with np.load(camp / "truth" / "labels" / f"{sid}.npz") as z:
            kind, tree = z["kind"], z["tree_id"]
        for zb, (_, b) in zip(st["z_base"], bh.iterrows(), strict=True):
            d = np.hypot(b["x"], b["y"])
            if d > max_d:
                continue
            half = np.degrees(np.arcsin(min(b["dbh_m"] / 2 / d, 1.0)))
            a0 = np.degrees(np.arctan2(b["y"], b["x"]))
            cols = np.flatnonzero(np.abs((az - a0 + 180) % 360 - 180) <= 0.8 * half)
            rows = np.flatnonzero((el >= np.degrees(np.arctan2(zb + 1.0, d)))
                                  & (el <= np.degrees(np.arctan2(zb + 1.6, d))))
            if cols.size and rows.size:
                box = np.ix_(rows, cols)
                out.append(((kind[box] == KIND_STEM) & (tree[box] == b["tree_id"])).mean())
    return np.array(out)


def test_understorey_and_stubs_hide_parts_of_trunks(campaigns):
    circ, real = (_breast_height_views(c) for c in campaigns)
    assert len(circ) >= 10 and len(real) >= 10
    partial = [np.mean((v > 0.1) & (v < 0.9)) for v in (circ, real)]
    assert real.mean() < circ.mean() - 0.03  # less of the trunks seen at breast height
    assert partial[1] > partial[0] + 0.03  # more trunks seen only in part


def test_stems_option_and_bad_values(tmp_path):
    from forestmap_assets.cli import main

    out = tmp_path / "r"
    assert main(["--quiet", "simulate", str(out), "--scans", "1", "--trees", "6", "--plot-size",
                 "16", "--resolution", "quarter", "--stems", "realistic"]) == 0
    assert "flattening" in pd.read_csv(out / "truth" / "stems.csv").columns
    with pytest.raises(ValueError, match="stems"):
        make_forest(5, 20.0, n_scans=1, stems="square")
    with pytest.raises(ValueError, match="stems"):
        simulate_campaign(tmp_path / "c", site="corridor", stems="realistic")
