"""Scans whose campaign gives no tilt are levelled from their shared stems (beyond the thesis:
core/mapping/levelling.py, orchestration/levelling.py) and the run goes again with them."""

from __future__ import annotations

import pandas as pd
import pytest
import yaml

from forestmap_assets.io.levelling_file import read_levelling
from forestmap_assets.orchestration.runner import run_campaign
from forestmap_assets.sim import simulate_campaign
from forestmap_assets.sim.evaluate import pose_errors

TILTS = [(0.0, 0.0), (0.6, -0.3), (-0.2, 0.55)]


def _tilted_campaign(tmp_path, monkeypatch, params: dict | None = None):
    """An own half-resolution campaign whose scan files are tilted by ``TILTS`` while its
    ``campaign.yaml`` gives no tilt; returns the folder and the scan ids."""
    monkeypatch.setenv("FORESTMAP_HOME", str(tmp_path / "home"))
    monkeypatch.setenv("DAGSTER_HOME", str(tmp_path / "home" / "dagster"))
    root = simulate_campaign(tmp_path / "plot", scans=3, trees=30, plot_size=30.0, seed=7, resolution="half",
                             tilt_deg=TILTS)
    doc = yaml.safe_load((root / "campaign.yaml").read_text())
    for scan in doc["scans"]:
        scan.pop("tilt_deg", None)  # the files are tilted, the campaign does not say so
    if params:
        doc["params"] = params
    (root / "campaign.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    return root, [s["id"] for s in doc["scans"]]


def _pose_errors(root) -> pd.DataFrame:
    from forestmap_assets.access import load_asset

    poses = load_asset("optimal_map", campaign=root)["poses"]
    return pose_errors(poses, pd.read_csv(root / "truth" / "poses.csv"))


@pytest.mark.slow
def test_tilted_scans_without_tilt_are_levelled_and_placed(tmp_path, monkeypatch):
    root, ids = _tilted_campaign(tmp_path, monkeypatch)
    lines, ready = [], []
    summary = run_campaign(root, progress=lines.append, map_ready=ready.append)
    assert summary.failures == []
    assert any("levelled by levelling.yaml" in line for line in lines), lines
    # the map's files once, from the levelled map; where to scan next only from that map (the
    # first pass stops after its map's stages)
    assert len(ready) == 1
    assert [stage for stage, _ in summary.ran].count("next_vantage_points") == 1
    estimates, rounds = read_levelling(root)
    assert rounds == 1 and set(estimates) == set(ids[1:])
    for sid, truth in zip(ids[1:], TILTS[1:], strict=True):
        assert estimates[sid]["tilt_deg"] == pytest.approx(truth, abs=0.1), (sid, estimates[sid])
        assert estimates[sid]["from_tilt_deg"] == (0.0, 0.0)
    err = _pose_errors(root)
    assert err["exy"].max() < 0.01 and err["ez"].abs().max() < 0.01, err
    # the next run finds everything levelled and fresh
    assert run_campaign(root, progress=lambda m: None).ran == []


@pytest.mark.slow
def test_without_levelling_the_same_scans_are_off(tmp_path, monkeypatch):
    """The case above with ``mapping.levelling: false``: the tilts stay in, and the poses are
    centimetres off (what the levelling is for)."""
    root, _ = _tilted_campaign(tmp_path, monkeypatch, params={"mapping": {"levelling": False}})
    assert run_campaign(root, progress=lambda m: None).failures == []
    assert not (root / "levelling.yaml").exists()
    assert _pose_errors(root)["ez"].abs().max() > 0.02


@pytest.mark.slow
def test_a_campaign_folder_that_cannot_take_the_file_still_gets_its_map(tmp_path, monkeypatch):
    import forestmap_assets.orchestration.levelling as levelling

    def refuse(root, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(root / "levelling.yaml"))

    monkeypatch.setattr(levelling, "write_levelling", refuse)
    root, _ = _tilted_campaign(tmp_path, monkeypatch)
    lines, ready = [], []
    summary = run_campaign(root, progress=lines.append, map_ready=ready.append)
    assert summary.failures == [] and len(ready) == 1
    assert any("cannot be written (Permission denied); the map keeps their tilt" in line for line in lines), lines
    assert "next_vantage_points" in {stage for stage, _ in summary.ran}  # after the map's files
    assert not (root / "levelling.yaml").exists()
