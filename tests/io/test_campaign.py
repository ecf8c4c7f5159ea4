"""campaign.yaml loading and validation (DESIGN.md section 2)."""

from __future__ import annotations

import pytest
from helpers.campaign_files import write_campaign

from forestmap_assets.io.campaign import CampaignError, load_campaign
from forestmap_assets.params import PRESETS, resolve_params


def test_valid_campaign_defaults(tmp_path):
    c = load_campaign(write_campaign(tmp_path / "plot"))
    assert c.name == "test-campaign" and c.key == "test_campaign"
    assert c.scan_ids == ["T", "S"]
    assert c.scans[0].tilt_deg == (0.0, 0.0) and c.pairs == ()
    assert c.params.segmentation.range_step_m == 0.11
    assert c.params.cylinders.min_length_m == 0.5


def test_pairs_search_params_and_sensor(tmp_path):
    extra = (
        "pairs:\n  - {scan: S, reference: T, a_priori: [3.0, -1.0, 1.0, -30.0]}\n"
        "search: {xy_m: 4.0, z_m: 1.0, heading_deg: 45}\n"
        "params:\n  cylinders: {min_length_m: 0.7}\n"
        "sensor: {angular_step_deg: 0.108, beam_divergence_mrad: 0.35, beam_exit_mm: 3.5}\n"
    )
    c = load_campaign(write_campaign(tmp_path / "p", extra=extra))
    assert c.pairs[0].scan == "S" and c.pairs[0].a_priori == (3.0, -1.0, 1.0, -30.0)
    assert c.params.cylinders.min_length_m == 0.7
    assert c.params.registration.xy_m == 4.0 and c.params.registration.heading_deg == 45.0
    assert c.angular_step_deg == 0.108 and c.name == "test-campaign"
    # the beam sets the refinement's (issue 19); an explicit params.refine value wins
    assert c.params.refine.beam_divergence_mrad == 0.35 and c.params.refine.beam_exit_m == pytest.approx(0.0035)
    # and the silhouette edges the DBH slice leaves out
    assert c.params.trees.beam_divergence_mrad == 0.35 and c.params.trees.beam_exit_m == pytest.approx(0.0035)
    # a named beam gives the DBH the silhouettes' widths (core/mapping/stem_calipers.py)
    assert c.params.trees.calipers and c.params.trees.caliper_widening == "beam"
    c = load_campaign(write_campaign(tmp_path / "q", extra="sensor: {beam_divergence_mrad: 3}\n"
                                     "params:\n  refine: {beam_divergence_mrad: 1.0}\n  trees: {calipers: false}\n"))
    assert c.params.refine.beam_divergence_mrad == 1.0 and c.params.refine.beam_exit_m == 0.0
    assert not c.params.trees.calipers
    # without the beam a forest takes the widths less their widening, from its own trees
    c = load_campaign(write_campaign(tmp_path / "r", extra="sensor: {angular_step_deg: 0.1}\n"))
    assert c.params.trees.calipers and c.params.trees.caliper_widening == "campaign"


@pytest.mark.parametrize(
    ("extra", "expected"),
    [
        ("colour: red\n", "colour: unknown key"),
        ("pairs:\n  - {scan: S, reference: X, a_priori: [0, 0, 0, 0]}\n", "pairs[0].reference: unknown scan id 'X'"),
        ("pairs:\n  - {scan: S, reference: T, a_priori: [0, 0, 0]}\n", "pairs[0].a_priori: expected a list of 4 numbers"),
        ("pairs:\n  - {scan: S, reference: T}\n", "pairs[0].a_priori: missing"),
        ("pairs:\n  - {scan: S, reference: S, a_priori: [0, 0, 0, 0]}\n", "same scan"),
        ("params:\n  cylinders: {min_length: 0.7}\n", "params.cylinders.min_length"),
        ("params:\n  cylinders: {min_length_m: lots}\n", "params.cylinders.min_length_m"),
        ("params:\n  magic: {x: 1}\n", "params.magic: unknown stage"),
        ("search: {xy_m: -1}\n", "search.xy_m: expected a positive number"),
        ("sensor: {angular_step_deg: zero}\n", "sensor.angular_step_deg"),
        ("sensor: {beam_divergence_mrad: -1}\n", "sensor.beam_divergence_mrad: expected a number >= 0"),
    ],
)
def test_manifest_errors_name_file_and_field(tmp_path, extra, expected):
    root = write_campaign(tmp_path / "bad", extra=extra)
    with pytest.raises(CampaignError) as err:
        load_campaign(root)
    message = str(err.value)
    assert "\n" not in message
    assert str(root / "campaign.yaml") in message
    assert expected in message


def test_duplicate_ids_missing_files_and_types(tmp_path):
    root = write_campaign(tmp_path / "c")
    manifest = root / "campaign.yaml"
    manifest.write_text("scans:\n  - {id: T, path: scans/T.npz}\n  - {id: T, path: scans/S.npz}\n")
    with pytest.raises(CampaignError, match=r"scans\[1\]\.id: duplicate scan id 'T'"):
        load_campaign(root)
    manifest.write_text("scans:\n  - {id: T, path: scans/nothere.npz}\n")
    with pytest.raises(CampaignError, match=r"scans\[0\]\.path: file not found"):
        load_campaign(root)
    manifest.write_text("scans:\n  - {id: T, path: scans/T.npz, tilt_deg: flat}\n")
    with pytest.raises(CampaignError, match=r"scans\[0\]\.tilt_deg: expected a list of 2 numbers"):
        load_campaign(root)
    manifest.write_text("scans:\n  - {id: 'T T', path: scans/T.npz}\n")
    with pytest.raises(CampaignError, match=r"scans\[0\]\.id"):
        load_campaign(root)
    manifest.write_text("environment: swamp\nscans:\n  - {id: T, path: scans/T.npz}\n")
    with pytest.raises(CampaignError, match="environment"):
        load_campaign(root)
    manifest.write_text("scans: [\n")
    with pytest.raises(CampaignError, match="not valid YAML"):
        load_campaign(root)
    with pytest.raises(CampaignError, match="missing campaign manifest"):
        load_campaign(tmp_path)


def test_presets_follow_thesis_tables():
    indoor, outdoor, forest = (resolve_params(e) for e in ("indoor", "outdoor", "forest"))
    assert indoor.segmentation.min_width_m == 0.2 and forest.segmentation.min_width_m == 0.06
    assert indoor.circles.symmetry_threshold_m == 0.0007 and forest.circles.symmetry_threshold_m == 0.0041
    assert indoor.cylinders.min_length_m == 1.0 and outdoor.cylinders.min_length_m == 0.3
    assert outdoor.cylinders.curvature_deg == 10.0 and forest.cylinders.curvature_deg == 12.0
    assert indoor.lines.min_length_m == 2.0 and outdoor.lines.min_length_m == 1.5
    assert forest.registration.sigma_m == 0.035 and forest.registration.final_cell_m == 0.02
    # a forest's colour scans are refined both ways (point to plane), not by hue-assisted ICP
    assert forest.refine.method == "point_to_plane" and outdoor.refine.method == "auto"
    assert set(PRESETS) == {"forest", "outdoor", "indoor"}
    # a parameter change changes exactly that stage's digest
    changed = resolve_params("forest", {"cylinders": {"min_length_m": 0.7}})
    assert changed.digest("cylinders") != forest.digest("cylinders")
    assert changed.digest("circles") == forest.digest("circles")
