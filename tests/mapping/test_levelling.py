"""Scans levelled from their shared stems (core/mapping/levelling.py, io/levelling_file.py)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from forestmap_assets.core.features.range_image import levelling_rotation
from forestmap_assets.core.mapping.levelling import (
    compose_tilt,
    link_tilt,
    needs_levelling,
    solve_tilts,
)


def _stems(rng, n=25, half=15.0):
    """Leaning stems (lean up to 5 deg) as cylinder pieces of 1-2 m from 0 to 8 m."""
    rows = []
    for _ in range(n):
        base = rng.uniform(-half, half, 2)
        lean = np.radians(rng.uniform(0, 5)) * np.array([np.cos(a := rng.uniform(0, 2 * np.pi)), np.sin(a)])
        z = 0.0
        while z < 8.0:
            z1 = min(8.0, z + rng.uniform(1.0, 2.0))
            rows.append((*(base + lean * z), z, *(base + lean * z1), z1))
            z = z1
    return np.array(rows)  # (k, 6): x0 y0 z0 x1 y1 z1


def _view(seg: np.ndarray, tilt_deg, pose, rng, noise_m=0.001) -> pd.DataFrame:
    """The cylinders as a scan sees them: world = R_z(h) L^T p + t for its points p, so
    p = L R_z(-h) (world - t); L the levelling rotation of the scan's tilt."""
    dx, dy, dz, h = pose
    c, s = np.cos(np.radians(h)), np.sin(np.radians(h))
    rz_inv = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])
    tilt = levelling_rotation(*tilt_deg)  # maps the scan's frame to level: its inverse tilts
    ends = []
    for k in (0, 3):
        w = seg[:, k:k + 3] - np.array([dx, dy, dz])
        ends.append((w @ rz_inv.T) @ tilt + rng.normal(0, noise_m, w.shape))
    df = pd.DataFrame(np.hstack(ends), columns=["x0", "y0", "z0", "x1", "y1", "z1"])
    return df.assign(radius_m=0.15, n_circles=20)


def test_link_tilt_reads_the_scans_relative_tilt():
    rng = np.random.default_rng(3)
    seg = _stems(rng)
    ref = _view(seg, (0.0, 0.0), (0, 0, 0, 0), rng)
    pose = (6.0, -3.0, 0.4, 50.0)
    scan = _view(seg, (0.4, -0.25), pose, rng)
    got = link_tilt(scan, ref, pose)
    assert got["n_tilt"] >= 15  # stems
    assert got["tilt_x_deg"] == pytest.approx(0.4, abs=0.04)
    assert got["tilt_y_deg"] == pytest.approx(-0.25, abs=0.04)
    assert got["sd_tilt_deg"] < 0.02
    level = link_tilt(_view(seg, (0.0, 0.0), pose, rng), ref, pose)
    assert np.hypot(level["tilt_x_deg"], level["tilt_y_deg"]) < 0.04
    # the reference's stems grouped once for all its pairs (scan_tilts) give the same tilt
    from forestmap_assets.core.mapping.stem_groups import group_stems

    assert link_tilt(scan, ref, pose, ref_stems=group_stems(ref)) == got


def test_link_tilt_needs_shared_stems():
    rng = np.random.default_rng(4)
    a = _view(_stems(rng), (0, 0), (0, 0, 0, 0), rng)
    b = _view(_stems(rng) + 100.0 * np.array([1, 0, 0, 1, 0, 0]), (0, 0), (0, 0, 0, 0), rng)
    got = link_tilt(a, b, (0, 0, 0, 0))
    assert got["n_tilt"] == 0 and np.isnan(got["tilt_x_deg"])


def test_solve_tilts_places_every_scan_against_the_reference():
    rng = np.random.default_rng(5)
    seg = _stems(rng, n=30)
    truth = {"A": (0.0, 0.0), "B": (0.5, 0.1), "C": (-0.2, 0.6)}
    poses = {"A": (0, 0, 0, 0), "B": (8.0, 2.0, 0.2, 120.0), "C": (-5.0, 7.0, -0.3, -70.0)}
    cyl = {k: _view(seg, truth[k], poses[k], rng) for k in truth}
    rows = []
    for i, j in (("B", "A"), ("C", "A"), ("C", "B")):
        # the pose of i in j's frame, for the tilt's heading: R_z(h_i - h_j)
        hi, hj = poses[i][3], poses[j][3]
        c, s = np.cos(np.radians(-hj)), np.sin(np.radians(-hj))
        d = np.array(poses[i][:2]) - np.array(poses[j][:2])
        rel = (c * d[0] - s * d[1], s * d[0] + c * d[1], poses[i][2] - poses[j][2], hi - hj)
        rows.append({"scan": i, "reference": j, "dheading_deg": rel[3], **link_tilt(cyl[i], cyl[j], rel)})
    tilts = solve_tilts(pd.DataFrame(rows), ["A", "B", "C"], "A").set_index("scan")
    for k, (r, p) in truth.items():
        assert tilts.loc[k, "roll_deg"] == pytest.approx(r, abs=0.03)
        assert tilts.loc[k, "pitch_deg"] == pytest.approx(p, abs=0.03)
    flagged = needs_levelling(tilts.reset_index(), 0.04, 4.0)
    assert set(flagged["scan"]) == {"B", "C"}


def test_solve_tilts_leaves_out_a_link_that_disagrees_and_unreached_scans():
    links = pd.DataFrame({"scan": ["B", "C", "C"], "reference": ["A", "A", "B"], "dheading_deg": [0.0, 0.0, 0.0],
                          "tilt_x_deg": [0.3, 0.1, 2.0], "tilt_y_deg": [0.0, 0.0, 0.0],
                          "sd_tilt_deg": [0.01, 0.01, 0.01], "n_tilt": [30, 30, 30]})
    tilts = solve_tilts(links, ["A", "B", "C", "D"], "A").set_index("scan")
    assert tilts.loc["B", "roll_deg"] == pytest.approx(0.3, abs=1e-6)
    assert tilts.loc["C", "roll_deg"] == pytest.approx(0.1, abs=1e-6)
    assert np.isnan(tilts.loc["D", "roll_deg"]) and tilts.loc["D", "n_links"] == 0


def test_compose_tilt_adds_the_correction_to_the_levelling():
    r, p = compose_tilt((0.3, -0.2), (-0.3, 0.2))
    assert abs(r) < 1e-3 and abs(p) < 1e-3
    r, p = compose_tilt((0.0, 0.0), (0.5, 0.1))
    assert (r, p) == pytest.approx((0.5, 0.1), abs=1e-9)


def _campaign(tmp_path, tilt_b=None):
    for s in ("A", "B"):
        (tmp_path / f"{s}.ply").write_bytes(b"")
    extra = f", tilt_deg: [{tilt_b[0]}, {tilt_b[1]}]" if tilt_b else ""
    (tmp_path / "campaign.yaml").write_text(
        "name: lev\nenvironment: forest\nscans:\n  - {id: A, path: A.ply}\n"
        f"  - {{id: B, path: B.ply{extra}}}\n")
    return tmp_path


def test_levelling_file_replaces_the_tilt_it_was_made_from(tmp_path):
    from forestmap_assets.io.campaign import load_campaign
    from forestmap_assets.io.levelling_file import read_levelling, write_levelling

    root = _campaign(tmp_path)
    write_levelling(root, "A", {"B": {"tilt_deg": (0.31, -0.12), "from_tilt_deg": (0.0, 0.0), "sd_deg": 0.02}}, 1)
    assert read_levelling(root)[1] == 1
    b = load_campaign(root).scan("B")
    assert b.tilt_deg == pytest.approx((0.31, -0.12)) and b.levelled_from == (0.0, 0.0)
    assert load_campaign(root).scan("A").levelled_from is None
    # the entry now says something else: the estimate no longer applies
    _campaign(tmp_path, tilt_b=(0.2, 0.1))
    b = load_campaign(root).scan("B")
    assert b.tilt_deg == (0.2, 0.1) and b.levelled_from is None


def test_a_bad_levelling_file_names_the_file_and_field(tmp_path):
    from forestmap_assets.io.campaign import CampaignError, load_campaign

    root = _campaign(tmp_path)
    (root / "levelling.yaml").write_text("scans:\n  B: {tilt_deg: [0.1], from_tilt_deg: [0, 0]}\n")
    with pytest.raises(CampaignError, match=r"levelling.yaml: scans.B.tilt_deg: expected two numbers"):
        load_campaign(root)


def test_links_of_levelled_scans_get_the_tilts_z_sd():
    from forestmap_assets.core.mapping.levelling import widen_levelled_links

    links = pd.DataFrame({"scan": ["B", "C"], "reference": ["A", "A"], "dx": [12.0, 5.0], "dy": [0.0, 0.0],
                          "sd_z": [0.001, 0.001]})
    out = widen_levelled_links(links, {"B": 0.005}, floor_deg=0.02)
    assert out["sd_z"].iloc[0] == pytest.approx(np.hypot(0.001, 12.0 * np.radians(0.02)))
    assert out["sd_z"].iloc[1] == 0.001  # neither scan levelled by an estimate
    assert widen_levelled_links(links, {}, 0.02) is links


def test_a_new_scan_is_levelled_after_the_rounds_but_an_estimate_is_not_refined_for_ever(tmp_path):
    from forestmap_assets.io.campaign import load_campaign
    from forestmap_assets.io.levelling_file import write_levelling
    from forestmap_assets.orchestration.levelling import MAX_ROUNDS, levelling_due

    root = _campaign(tmp_path)
    tilts = pd.DataFrame({"scan": ["A", "B"], "level": [False, True]})
    assert levelling_due(load_campaign(root), tilts)  # B has no estimate yet
    assert not levelling_due(load_campaign(root), tilts.assign(level=False))
    write_levelling(root, "A", {"B": {"tilt_deg": (0.5, 0.0), "from_tilt_deg": (0.0, 0.0), "sd_deg": 0.01}}, MAX_ROUNDS)
    assert not levelling_due(load_campaign(root), tilts)  # B levelled, no rounds left
    write_levelling(root, "A", {"B": {"tilt_deg": (0.5, 0.0), "from_tilt_deg": (0.0, 0.0), "sd_deg": 0.01}}, 1)
    assert levelling_due(load_campaign(root), tilts)
    # B's entry now gives another tilt: no estimate levels it, so it is levelled whatever the rounds
    write_levelling(root, "A", {"B": {"tilt_deg": (0.5, 0.0), "from_tilt_deg": (0.0, 0.0), "sd_deg": 0.01}}, MAX_ROUNDS)
    _campaign(tmp_path, tilt_b=(0.2, 0.1))
    assert levelling_due(load_campaign(root), tilts)
