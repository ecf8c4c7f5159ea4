"""Scanner poses from the files (issue 18): multi-scan E57 with stored poses, point clouds in a
project frame with ``pose:`` in campaign.yaml, and ``forestmap init``."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import yaml

from forestmap_assets.core.features.range_image import levelling_rotation
from forestmap_assets.core.geometry import (
    matrix_quaternion,
    quaternion_matrix,
    roll_pitch_heading,
    rotation_zyx,
)
from forestmap_assets.io.campaign import CampaignError, load_campaign
from forestmap_assets.io.campaign_init import init_campaign
from forestmap_assets.io.readers import ScanReadError, read_scan
from forestmap_assets.io.scan_poses import PoseError, parse_pose
from forestmap_assets.sim.campaign import simulate_campaign
from forestmap_assets.sim.scanner_exports import pack_e57, place_in_project_frame

TILT = (2.0, -1.5)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """A small tilted campaign (quarter resolution, 3 scans) in npz."""
    out = tmp_path_factory.mktemp("poses") / "npz"
    simulate_campaign(out, scans=3, trees=15, plot_size=20.0, seed=5, resolution="quarter",
                      no_prior=True, tilt_deg=TILT, write_labels=False)
    return out


def _copy(simulated, tmp_path, name):
    dst = tmp_path / name
    shutil.copytree(simulated, dst)
    return dst


def test_pose_conventions_round_trip():
    for r, p, h in [(1.0, 2.0, 3.0), (-3.0, 4.0, -120.0), (0.0, 0.0, 179.5)]:
        m = rotation_zyx(r, p, h)
        assert np.allclose(roll_pitch_heading(m), (r, p, h))
        assert np.allclose(quaternion_matrix(*matrix_quaternion(m)), m, atol=1e-12)
    # the roll and pitch of a pose are the levelling tilt of the scan
    assert np.allclose(rotation_zyx(*TILT, 0.0), levelling_rotation(*TILT))


def test_parse_pose_dict_and_matrix_and_errors():
    p = parse_pose({"x": 512345.12, "y": 6712345.67, "z": 101.3, "heading_deg": 37.0,
                    "roll_deg": 0.1, "pitch_deg": -0.2})
    assert np.allclose(p.tilt_deg, (0.1, -0.2)) and np.allclose(p.a_priori, (512345.12, 6712345.67, 101.3, 37.0))
    q = parse_pose(p.matrix.tolist())
    assert np.allclose(q.matrix, p.matrix)
    with pytest.raises(PoseError) as e:
        parse_pose({"x": 1, "y": 2})
    assert e.value.key == "z"
    with pytest.raises(PoseError):
        parse_pose((2 * np.eye(4)).tolist())  # scaled: not a rotation
    with pytest.raises(PoseError):
        parse_pose({"x": 1, "y": 2, "z": 3, "yaw": 4})


def test_bad_pose_in_campaign_names_file_and_field(simulated, tmp_path):
    camp = _copy(simulated, tmp_path, "bad")
    doc = yaml.safe_load((camp / "campaign.yaml").read_text())
    doc["scans"][0]["pose"] = {"x": 1.0, "y": 2.0}
    (camp / "campaign.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(CampaignError, match=r"campaign.yaml: scans\[0\].pose: only for point-cloud"):
        load_campaign(camp)


def test_multi_scan_e57_gives_one_scan_each_with_tilt_and_prior_from_its_pose(simulated, tmp_path):
    camp = _copy(simulated, tmp_path, "e57")
    originals = {s.id: read_scan(s.path) for s in load_campaign(camp).scans}
    pack_e57(camp, prior_error=(0.3, 3.0), seed=1)
    c = load_campaign(camp)
    assert len({s.path for s in c.scans}) == 1 and [s.e57_scan for s in c.scans] == [0, 1, 2]
    for s in c.scans:
        assert np.allclose(s.tilt_deg, TILT, atol=1e-9)  # levelling from the stored pose
        assert s.prior_source == "e57 pose" and s.a_priori is not None
        img = read_scan(s.path, scan_index=s.e57_scan)  # points in the scan's own frame
        assert np.array_equal(np.isnan(img.range_m), np.isnan(originals[s.id].range_m))
        assert np.nanmax(np.abs(img.range_m - originals[s.id].range_m)) < 1e-6
    # relative a priori poses are the truth within the injected error
    a = {s.id: np.array(s.a_priori) for s in c.scans}
    d = np.linalg.norm(a["S"][:2] - a["T"][:2])
    truth = np.loadtxt(camp / "truth" / "poses.csv", delimiter=",", skiprows=1, usecols=(1, 2))
    assert abs(d - np.linalg.norm(truth[1] - truth[0])) < 2.0


def test_a_priori_from_file_false_keeps_the_tilt_only(simulated, tmp_path):
    camp = _copy(simulated, tmp_path, "nofile")
    pack_e57(camp)
    doc = yaml.safe_load((camp / "campaign.yaml").read_text())
    doc["a_priori_from_file"] = False
    (camp / "campaign.yaml").write_text(yaml.safe_dump(doc))
    c = load_campaign(camp)
    assert all(s.a_priori is None and np.allclose(s.tilt_deg, TILT) for s in c.scans)


def test_multi_scan_e57_entry_without_index_is_a_one_line_error(simulated, tmp_path):
    camp = _copy(simulated, tmp_path, "noindex")
    pack_e57(camp)
    doc = yaml.safe_load((camp / "campaign.yaml").read_text())
    del doc["scans"][1]["e57_scan"]
    (camp / "campaign.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(CampaignError, match=r"scans\[1\].e57_scan: survey.e57 holds 3 scans"):
        load_campaign(camp)
    with pytest.raises(ScanReadError, match="holds 3 scans; give e57_scan"):
        read_scan(camp / "scans" / "survey.e57")


def test_init_lists_every_e57_scan_with_its_pose(simulated, tmp_path):
    camp = _copy(simulated, tmp_path, "init_e57")
    e57 = pack_e57(camp)
    out = tmp_path / "fresh"
    manifest, found = init_campaign(e57, out)
    assert [f.e57_scan for f in found] == [0, 1, 2] and [f.id for f in found] == ["T", "S", "R"]
    assert all("pose in file" in f.notes[0] for f in found)
    c = load_campaign(out)
    assert all(s.prior_source == "e57 pose" for s in c.scans)
    with pytest.raises(CampaignError, match="already exists"):
        init_campaign(e57, out)


def test_init_on_a_folder_of_project_frame_las_says_so(simulated, tmp_path):
    camp = _copy(simulated, tmp_path, "init_las")
    place_in_project_frame(camp, "las")
    (camp / "campaign.yaml").unlink()
    manifest, found = init_campaign(camp)
    assert len(found) == 3 and all("project frame" in f.notes[0] for f in found)
    assert "# T: points in a project frame" in manifest.read_text()


@pytest.mark.parametrize("fmt", ["las", "ply"])
def test_project_frame_cloud_is_moved_to_its_scanner_before_projection(simulated, tmp_path, fmt):
    """UTM-sized coordinates keep their millimetres: the scan read through its ``pose`` is the
    scan written in the scanner's own frame."""
    from forestmap_assets.io.writers import write_scan

    camp = _copy(simulated, tmp_path, f"proj_{fmt}")
    c0 = load_campaign(camp)
    local = {}
    for s in c0.scans:
        local[s.id] = tmp_path / f"{s.id}_local.{fmt}"
        write_scan(local[s.id], read_scan(s.path, angular_step_deg=c0.angular_step_deg))
    place_in_project_frame(camp, fmt)
    c = load_campaign(camp)
    for s in c.scans:
        assert s.pose is not None and s.prior_source == "pose" and np.allclose(s.tilt_deg, TILT)
        assert abs(s.a_priori[0]) > 1e5  # map coordinates
        moved = read_scan(s.path, angular_step_deg=c.angular_step_deg, to_scanner=s.to_scanner)
        ref = read_scan(local[s.id], angular_step_deg=c.angular_step_deg)
        assert moved.shape == ref.shape
        both = np.isfinite(moved.range_m) & np.isfinite(ref.range_m)
        assert both.sum() >= 0.999 * np.isfinite(ref.range_m).sum()
        assert np.max(np.abs(moved.range_m[both] - ref.range_m[both])) < 1e-3
        # without the pose the file is projected about the map origin: nothing like the scan
        wrong = read_scan(s.path, angular_step_deg=c.angular_step_deg)
        assert np.nanmedian(wrong.range_m) > 1e5


def test_unregistered_e57_gives_the_tilt_but_no_prior(simulated, tmp_path):
    camp = _copy(simulated, tmp_path, "tiltonly")
    pack_e57(camp, with_prior=False)
    c = load_campaign(camp)
    assert all(s.a_priori is None and np.allclose(s.tilt_deg, TILT) for s in c.scans)


@pytest.mark.slow
@pytest.mark.parametrize("layout", ["e57-multi", "las-project-frame"])
def test_scanner_exports_register_end_to_end(tmp_path, layout):
    """A day's multi-scan E57 (tilt and rough poses in the file) and LAS files in a UTM-like
    project frame (poses in campaign.yaml) both give every scan within 3 cm of the truth."""
    import pandas as pd

    from forestmap_assets.cli import main

    camp = tmp_path / layout
    simulate_campaign(camp, scans=3, trees=25, plot_size=25.0, seed=7, resolution="quarter",
                      no_prior=True, tilt_deg=TILT, write_labels=False)
    if layout == "e57-multi":
        pack_e57(camp, prior_error=(0.5, 5.0), seed=2)
    else:
        place_in_project_frame(camp, "las")
    assert main(["run", str(camp), "--no-cloud", "--no-report", "-q"]) == 0
    got = pd.read_csv(camp / "outputs" / "poses.csv").set_index("scan")
    truth = pd.read_csv(camp / "truth" / "poses.csv").set_index("scan")
    assert got["registered"].all()
    err = np.hypot(got["x"] - truth["x"], got["y"] - truth["y"])
    assert err.max() < 0.03, err
    dh = (got["heading_deg"] - truth["heading_deg"] + 180) % 360 - 180
    assert dh.abs().max() < 0.3
