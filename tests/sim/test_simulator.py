"""Virtual forest and Riegl LMS-Z210-like scanner (spec 1.1-1.2, 10.1, 10.6; DESIGN.md 2-3).

Small plots at quarter resolution so the whole file runs in seconds.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import yaml
from helpers.beam_scenes import POLE_GRID, pole_before_wall

from forestmap_assets.core.features.range_image import RangeImage
from forestmap_assets.sim import ScanPose, VirtualScanner, make_forest, simulate_campaign
from forestmap_assets.sim.scene_mesh import KIND_GROUND, KIND_STEM

SMALL = dict(scans=3, trees=20, plot_size=30.0, seed=3, resolution="quarter")
NOISE_FREE = {"range_sigma_m": 0.0}


def _rot_z(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _load(camp, sid, tilt=None):
    """Range image of scan ``sid`` read back from the npz, with the tilt of campaign.yaml."""
    doc = yaml.safe_load((camp / "campaign.yaml").read_text())
    entry = next(e for e in doc["scans"] if e["id"] == sid)
    with np.load(camp / entry["path"]) as z:
        rng, az, el = z["range"], z["azimuth_deg"], z["elevation_deg"]
    tilt = tuple(entry.get("tilt_deg", (0.0, 0.0))) if tilt is None else tilt
    with np.load(camp / "truth" / "labels" / f"{sid}.npz") as z:
        labels = {k: z[k] for k in z.files}
    return RangeImage(rng, az, el, tilt), labels


def _global_points(camp, sid, img):
    """Levelled points of a scan moved into the global frame with truth/poses.csv."""
    pose = pd.read_csv(camp / "truth" / "poses.csv").set_index("scan").loc[sid]
    return img.xyz @ _rot_z(pose["heading_deg"]).T + pose[["x", "y", "z"]].to_numpy(float)


def _stem_errors(camp, sid, tilt=None):
    """Signed distance error |p - axis| - r(h, psi) of stem hits, with h, range and mixed flag."""
    img, lab = _load(camp, sid, tilt)
    pts = _global_points(camp, sid, img)
    sel = (lab["kind"] == KIND_STEM) & img.valid
    stems = pd.read_csv(camp / "truth" / "stems.csv").set_index("tree_id")
    s = stems.loc[lab["tree_id"][sel]]
    p = pts[sel]
    lean = np.column_stack([s["lean_x"], s["lean_y"], np.ones(len(s))])
    norm = np.linalg.norm(lean, axis=1, keepdims=True)
    a = lean / norm
    base = s[["x_base", "y_base", "z_base"]].to_numpy()
    t = ((p - base) * a).sum(1)
    foot = base + t[:, None] * a
    v = p - foot
    dist = np.linalg.norm(v, axis=1)
    h = t / norm[:, 0]  # vertical height of the foot point above the base
    e1 = np.array([1.0, 0.0, 0.0]) - a[:, :1] * a
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(a, e1)
    psi = np.arctan2((v * e2).sum(1), (v * e1).sum(1))
    r = (s["r_base_m"].to_numpy() - s["taper_m_per_m"].to_numpy() * h
         + s["a2_m"].to_numpy() * np.cos(2 * (psi - np.radians(s["phase2_deg"].to_numpy())))
         + s["a3_m"].to_numpy() * np.cos(3 * (psi - np.radians(s["phase3_deg"].to_numpy()))))
    return pd.DataFrame({"err": dist - r, "h": h, "range": img.range_m[sel],
                         "mixed": lab["mixed"][sel]})


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    return simulate_campaign(tmp_path_factory.mktemp("a") / "camp", **SMALL)


@pytest.fixture(scope="module")
def clean_campaign(tmp_path_factory):
    return simulate_campaign(tmp_path_factory.mktemp("clean") / "camp", **SMALL,
                             scanner_kwargs=NOISE_FREE)


def test_deterministic_bytes(campaign, tmp_path):
    again = simulate_campaign(tmp_path / "b" / "camp", **SMALL)
    files = sorted(p.relative_to(campaign) for p in campaign.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    assert len(files) >= 3 + 3 + 3 + 1  # scans, labels, truth csvs, campaign.yaml
    for f in files:
        assert (campaign / f).read_bytes() == (again / f).read_bytes(), f
    other = simulate_campaign(tmp_path / "c" / "camp", **{**SMALL, "seed": 4})
    with np.load(campaign / "scans" / "T.npz") as a, np.load(other / "scans" / "T.npz") as b:
        assert not np.array_equal(a["range"], b["range"], equal_nan=True)


def test_campaign_layout_and_truth_headers(campaign):
    doc = yaml.safe_load((campaign / "campaign.yaml").read_text())
    assert doc["environment"] == "forest" and doc["name"] == "camp"
    assert [e["id"] for e in doc["scans"]] == ["T", "S", "R"]
    assert all("tilt_deg" not in e for e in doc["scans"])
    assert (campaign / "truth" / "poses.csv").read_text().splitlines()[0] == (
        "scan,x,y,z,heading_deg")
    assert (campaign / "truth" / "trees.csv").read_text().splitlines()[0] == (
        "tree_id,x,y,z,dbh_m,n_visible_scans")
    poses = pd.read_csv(campaign / "truth" / "poses.csv")
    assert list(poses["scan"]) == ["T", "S", "R"]
    assert np.allclose(poses.iloc[0, 1:].to_numpy(float), 0.0)
    assert (poses["heading_deg"] > -180).all() and (poses["heading_deg"] <= 180).all()
    step = np.linalg.norm(np.diff(poses[["x", "y"]].to_numpy(), axis=0), axis=1)
    assert ((step > 4.5) & (step < 10.5)).all()  # neighbours 5-10 m apart
    trees = pd.read_csv(campaign / "truth" / "trees.csv")
    assert len(trees) == 20 and trees["tree_id"].is_unique
    assert trees["dbh_m"].between(0.07, 0.60).all()
    assert trees["n_visible_scans"].between(0, 3).all()
    assert (trees["n_visible_scans"] >= 2).sum() >= 5
    # ground under the stems lies about a tripod height below the first scanner
    assert trees["z"].between(-1.5 - 1.5, -1.5 + 1.5).all()
    # the stem table reproduces trees.csv at breast height
    stems = pd.read_csv(campaign / "truth" / "stems.csv")
    h = 1.3
    assert np.allclose(stems["x_base"] + stems["lean_x"] * h, trees["x"], atol=1e-5)
    assert np.allclose(2 * (stems["r_base_m"] - stems["taper_m_per_m"] * h), trees["dbh_m"],
                       atol=1e-5)
    # the image geometry of a quarter-resolution LMS-Z210 (spec 1.1-1.2)
    with np.load(campaign / "scans" / "T.npz") as z:
        assert z["range"].shape == (180, 750) and z["range"].dtype == np.float32
        az, el = z["azimuth_deg"], z["elevation_deg"]
        assert np.allclose(np.diff(az), 330 / 750) and np.allclose(np.diff(el), -79 / 180)
        assert np.isclose(az[0], -az[-1]) and np.isclose(el[0], -el[-1])
        assert np.isnan(z["range"][0]).mean() > 0.05  # sky above the canopy gaps
        assert np.nanmax(z["range"]) <= 80.0 + 0.2


def test_visible_counts_follow_ray_hits(campaign):
    trees = pd.read_csv(campaign / "truth" / "trees.csv").set_index("tree_id")
    hit_in = pd.Series(0, index=trees.index)
    for sid in ("T", "S", "R"):
        img, lab = _load(campaign, sid)
        near = (lab["kind"] == KIND_STEM) & (img.range_m < 20.5)
        ids, counts = np.unique(lab["tree_id"][near], return_counts=True)
        hit_in.loc[ids[counts >= 5]] += 1  # >= 1 m of trunk is many pixels
    assert (trees["n_visible_scans"] <= hit_in).all()
    assert (trees.loc[hit_in == 0, "n_visible_scans"] == 0).all()


def test_stem_hits_lie_on_the_true_stems_noise_free(clean_campaign):
    for sid in ("T", "S", "R"):
        e = _stem_errors(clean_campaign, sid)
        centre = e[~e["mixed"]]
        assert len(centre) > 500
        # centre rays hit the faceted stem surface: within facet + float32 error
        assert np.quantile(np.abs(centre["err"]), 0.99) < 0.004
        edge = e[e["mixed"]]
        assert len(edge) > 50
        # first return from the beam edge: the point lies outside the stem ("wider" objects)
        # but no further than the footprint radius (0.042 + 0.003 r) / 2 (spec 1.1)
        assert edge["err"].min() > -0.004
        assert (edge["err"] <= (0.021 + 0.0015 * edge["range"]) + 0.004).all()
        assert edge["err"].mean() > 0.005


def test_stem_hits_at_breast_height_within_noise(campaign):
    e = pd.concat([_stem_errors(campaign, sid) for sid in ("T", "S", "R")])
    bh = e[e["h"].between(1.0, 1.6) & (e["range"] < 15)]
    centre = bh[~bh["mixed"]]
    assert len(centre) > 100
    # sigma 0.025 m along the ray -> mean |radial error| below 0.025 m, unbiased
    assert np.abs(centre["err"]).mean() < 0.025
    assert abs(centre["err"].median()) < 0.01
    # with the beam-widened edge pixels: a few cm, biased outwards
    assert np.abs(bh["err"]).mean() < 0.04
    assert bh["err"].mean() > centre["err"].mean()


def test_tilt_levelling_round_trip(tmp_path):
    kw = {**SMALL, "scans": 2}
    camp = simulate_campaign(tmp_path / "tilt", **kw, tilt_deg=(4.0, -3.0),
                             scanner_kwargs=NOISE_FREE)
    doc = yaml.safe_load((camp / "campaign.yaml").read_text())
    assert [e["tilt_deg"] for e in doc["scans"]] == [[4.0, -3.0], [4.0, -3.0]]
    level = simulate_campaign(tmp_path / "level", **kw, scanner_kwargs=NOISE_FREE)
    assert (camp / "truth" / "poses.csv").read_bytes() == (
        level / "truth" / "poses.csv").read_bytes()
    for sid in ("T", "S"):
        e = _stem_errors(camp, sid)  # levelled with R_y(pitch) R_x(roll) of range_image.py
        assert np.quantile(np.abs(e.loc[~e["mixed"], "err"]), 0.99) < 0.004
        wrong = _stem_errors(camp, sid, tilt=(0.0, 0.0))  # tilt ignored: points off the stems
        assert np.median(np.abs(wrong["err"])) > 0.05
    # ground near the tilted scanner, levelled, has the slope seen by the levelled scanner
    def ground_normal(camp, tilt=None):
        img, lab = _load(camp, "T", tilt)
        g = img.xyz[(lab["kind"] == KIND_GROUND) & (img.range_m < 5)]
        n = np.linalg.svd(g - g.mean(0), full_matrices=False)[2][2]
        return n * np.sign(n[2])

    def angle(a, b):
        return np.degrees(np.arccos(np.clip(a @ b, -1, 1)))

    truth = ground_normal(level)
    assert angle(ground_normal(camp), truth) < 0.3
    assert angle(ground_normal(camp, tilt=(0.0, 0.0)), truth) > 3.0


def test_no_prior_writes_no_pairs(tmp_path):
    camp = simulate_campaign(tmp_path / "np", **{**SMALL, "scans": 2}, no_prior=True)
    doc = yaml.safe_load((camp / "campaign.yaml").read_text())
    assert "pairs" not in doc and "search" not in doc
    assert [e["id"] for e in doc["scans"]] == ["T", "S"]


def _truth_relative(poses, scan, ref):
    a, b = poses.loc[scan], poses.loc[ref]
    d = _rot_z(-b["heading_deg"]) @ (a[["x", "y", "z"]].to_numpy(float)
                                      - b[["x", "y", "z"]].to_numpy(float))
    return d, (a["heading_deg"] - b["heading_deg"] + 180) % 360 - 180


def test_a_priori_error_bounded_by_prior_error(campaign, tmp_path):
    doc = yaml.safe_load((campaign / "campaign.yaml").read_text())
    poses = pd.read_csv(campaign / "truth" / "poses.csv").set_index("scan")
    order = [e["id"] for e in doc["scans"]]
    assert {p["scan"] for p in doc["pairs"]} == {"S", "R"}  # connected to T
    assert all(order.index(p["reference"]) < order.index(p["scan"]) for p in doc["pairs"])
    dt, dh = [], []
    for p in doc["pairs"]:
        d, h = _truth_relative(poses, p["scan"], p["reference"])
        dt.append(np.linalg.norm(np.array(p["a_priori"][:3]) - d))
        dh.append(abs((p["a_priori"][3] - h + 180) % 360 - 180))
    assert max(dt) <= 1.0 + 1e-3 and max(dh) <= 10.0 + 1e-3
    assert max(dt) > 0.01 and max(dh) > 0.01  # really perturbed
    s = doc["search"]
    assert s["xy_m"] >= 1.0 and s["z_m"] >= 1.0 and s["heading_deg"] >= 10.0
    # with no error the a priori is the true relative pose (checks the pair convention)
    exact = simulate_campaign(tmp_path / "exact", **{**SMALL, "scans": 2}, prior_error=(0, 0))
    doc = yaml.safe_load((exact / "campaign.yaml").read_text())
    poses = pd.read_csv(exact / "truth" / "poses.csv").set_index("scan")
    (pair,) = doc["pairs"]
    d, h = _truth_relative(poses, pair["scan"], pair["reference"])
    assert np.allclose(pair["a_priori"], [*d, h], atol=2e-4)


def test_forest_layout():
    f = make_forest(trees=60, plot_size=40.0, n_scans=6, seed=1)
    st = f.stems
    xy = st[["x_base", "y_base"]].to_numpy()
    r = st["r_base_m"].to_numpy()
    dist = np.linalg.norm(xy[:, None] - xy[None], axis=2) + np.eye(len(xy)) * 1e9
    assert (dist >= r[:, None] + r[None] + 0.8 - 1e-9).all()  # stems do not overlap
    to_scan = np.linalg.norm(xy[:, None] - f.scan_xy[None], axis=2)
    assert (to_scan >= 2.5).all()
    assert (np.abs(xy) <= 20).all()
    dbh = f.trees_at_breast_height()["dbh_m"]
    assert dbh.between(0.07, 0.60).all() and dbh.between(0.15, 0.35).mean() > 0.6
    lean = np.degrees(np.arctan(np.hypot(st["lean_x"], st["lean_y"])))
    assert lean.max() <= 8.0 + 1e-9 and lean.mean() > 0.5
    assert st["height_m"].between(8, 36).all() and (st["taper_m_per_m"] > 0).all()
    # crowns above ~2 m, understorey below ~1.6 m and clear of the tripods
    m = f.mesh
    v = m.vertices[m.triangles]  # (F, 3, 3)
    above = v[..., 2] - f.ground.height(v[..., 0], v[..., 1])
    foliage = m.kind == 3
    under = m.kind == 4
    assert above[foliage].min() > 1.5 and above[under].max() < 1.6
    near = np.linalg.norm(v[under][..., None, :2] - f.scan_xy, axis=-1)
    assert near.min() > 1.2
    # the ground is uneven: a slope plus a few dm of relief
    g = np.linspace(-20, 20, 41)
    z = f.ground.height(*np.meshgrid(g, g))
    assert 0.3 < np.ptp(z) < 4.0


def test_beam_footprint_widens_thin_objects():
    """A 0.2 m pole at 5 m in front of a wall at 15 m (spec 1.1: 0.042 m + 3 mrad beam)."""
    mesh, geo = pole_before_wall(), POLE_GRID
    pose = ScanPose(0.0, 0.0, 0.0)
    widths = {}
    for k in (0, 8):
        res = VirtualScanner(mesh, sub_rays=k, **geo).scan(pose, seed=1)
        az = np.radians(res.image.azimuth_deg)
        on = res.kind == KIND_STEM
        # apparent width of the pole per row: columns on the pole x pitch x range
        widths[k] = on.sum(1) * np.diff(az).mean() * 4.9
        if k == 0:
            assert not res.mixed.any()
        else:
            # mixed pixels return the near (pole) range, not the wall behind
            assert res.mixed.sum() >= 2 * 20
            assert (res.image.range_m[res.mixed] < 5.0).all()
        wall = res.kind == 0
        if k:  # a blended echo: ghost points between the pole's edge and the wall
            ghost = VirtualScanner(mesh, sub_rays=k, mixed_range="blend", **geo).scan(pose, seed=1)
            r = ghost.image.range_m[ghost.mixed]
            assert ghost.mixed.sum() == res.mixed.sum() and (r > 4.85).all() and (r < 15.6).all()
            assert np.mean(r > 6.0) > 0.5  # most well behind the pole's front
        assert np.allclose(res.image.range_m[wall] * np.cos(az)[None].repeat(20, 0)[wall]
                           * np.cos(np.radians(res.image.elevation_deg))[:, None]
                           .repeat(50, 1)[wall], 15.0, atol=1e-3)
    pitch = np.radians(0.11) * 4.9
    rho = 0.021 + 0.0015 * 4.9  # footprint radius at the pole
    assert np.all(np.abs(widths[0] - 0.2) <= 1.5 * pitch)
    extra = widths[8] - widths[0]
    assert np.all(extra >= 2 * rho * np.cos(np.pi / 8) - 2 * pitch)
    assert np.all(extra <= 2 * rho + 2 * pitch)


def test_other_formats_use_the_io_writers(tmp_path):
    pytest.importorskip("forestmap_assets.io.writers")
    camp = simulate_campaign(tmp_path / "las", **{**SMALL, "scans": 1}, fmt="las")
    doc = yaml.safe_load((camp / "campaign.yaml").read_text())
    assert doc["scans"][0]["path"] == "scans/T.las"
    assert (camp / "scans" / "T.las").stat().st_size > 1000


def test_rejects_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="resolution"):
        simulate_campaign(tmp_path / "x", resolution="eighth")
    with pytest.raises(ValueError, match="format"):
        simulate_campaign(tmp_path / "x", fmt="pcd")
    with pytest.raises(ValueError, match="cannot place"):
        make_forest(trees=400, plot_size=10.0, n_scans=2, seed=0)


def test_simulate_colour_writes_rgb_that_the_reader_keeps(tmp_path):
    """``forestmap simulate --colour``: every scan file carries RGB, bark and ground differ."""
    from forestmap_assets.cli import main
    from forestmap_assets.io.readers import read_scan

    out = tmp_path / "c"
    assert main(["--quiet", "simulate", str(out), "--scans", "2", "--trees", "8", "--plot-size", "16",
                 "--resolution", "quarter", "--colour"]) == 0
    for sid in ("T", "S"):
        image = read_scan(out / "scans" / f"{sid}.npz")
        assert image.rgb is not None and image.rgb.shape == image.range_m.shape + (3,)
        hit = np.isfinite(image.range_m)
        assert image.rgb[hit].std(axis=0).min() > 1.0  # not one flat colour
