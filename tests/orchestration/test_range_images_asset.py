"""The `range_images` asset materialised through Dagster (per-scan partitions, caching)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers.campaign_files import write_campaign

from forestmap_assets.core.features.range_image import RangeImage, levelling_rotation
from forestmap_assets.io.campaign import load_campaign
from forestmap_assets.io.store import read_table
from forestmap_assets.orchestration.definitions import build_definitions
from forestmap_assets.orchestration.instance import get_instance
from forestmap_assets.orchestration.runner import run_campaign
from forestmap_assets.orchestration.status import stage_states


def _stored(home, campaign, scan):
    return RangeImage.from_table(read_table(home / "store" / campaign.key / "range_images" / f"{scan}.parquet"))


@pytest.mark.slow
def test_range_images_materialise_level_and_cache(tmp_path, _isolated_home):
    root = write_campaign(tmp_path / "plot", scans=("T", "S", "R"), with_rgb=True)
    manifest = root / "campaign.yaml"
    manifest.write_text(manifest.read_text().replace("path: scans/S.npz}", "path: scans/S.npz, tilt_deg: [2.0, -1.0]}"))
    campaign = load_campaign(root)
    summary = run_campaign(root, progress=lambda m: None)
    assert summary.failures == []
    assert sorted(x for x in summary.ran if x[0] == "range_images") == [("range_images", s) for s in ("R", "S", "T")]

    raw = np.load(root / "scans" / "S.npz")
    image = _stored(_isolated_home, campaign, "S")
    assert image.shape == raw["range"].shape
    np.testing.assert_allclose(image.range_m, raw["range"], equal_nan=True)
    assert image.rgb is not None and np.array_equal(image.rgb[5], raw["rgb"][5])
    # levelled: the stored points are the sensor points rotated by R_y(pitch) R_x(roll)
    sensor = RangeImage(raw["range"], raw["azimuth_deg"], raw["elevation_deg"]).xyz
    expected = sensor @ levelling_rotation(2.0, -1.0).T
    np.testing.assert_allclose(image.xyz, expected, atol=1e-5, equal_nan=True)

    # second run: everything fresh, nothing re-runs
    assert run_campaign(root, progress=lambda m: None).ran == []
    defs = build_definitions([campaign])
    state = {s.stage: s for s in stage_states(defs, campaign, get_instance())}
    assert state["range_images"].state == "fresh"

    # a changed scan file re-runs only its own partition
    data = dict(np.load(root / "scans" / "T.npz"))
    data["range"] = data["range"] * 1.01
    np.savez(root / "scans" / "T.npz", **data)
    rerun = run_campaign(root, progress=lambda m: None).ran
    assert ("range_images", "T") in rerun
    parts = {part for _, part in rerun if part is not None}
    assert parts & set(campaign.scan_ids) == {"T"}  # no other scan's work
    assert all("T" in part.split("__") for part in parts - {"T"})  # and only the pairs with T


@pytest.mark.slow
def test_corrupt_scan_fails_only_its_partition(tmp_path, _isolated_home):
    root = write_campaign(tmp_path / "plot", scans=("T", "S"))
    (root / "scans" / "S.npz").write_bytes(b"this is not a numpy archive")
    summary = run_campaign(root, progress=lambda m: None)
    assert ("range_images", "T") in summary.ran
    assert {scan for _, scan in summary.ran if scan is not None} == {"T"}
    (stage, scan, reason), = summary.failures
    assert scan == "S" and "S.npz" in reason and "\n" not in reason
    store = _isolated_home / "store" / "test_campaign" / "range_images"
    assert sorted(p.name for p in store.iterdir()) == ["T.parquet"]
