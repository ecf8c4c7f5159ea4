"""The whole pipeline on simulated campaigns, measured against the simulator's truth."""

from __future__ import annotations

import pandas as pd
import pytest

from forestmap_assets.io.campaign import load_campaign
from forestmap_assets.orchestration.runner import run_campaign
from forestmap_assets.outputs.exports import write_exports
from forestmap_assets.sim import simulate_campaign
from forestmap_assets.sim.evaluate import evaluate_campaign


def _run(tmp_path, **sim):
    root = simulate_campaign(tmp_path / "plot", resolution="quarter", plot_size=30.0, trees=30, **sim)
    summary = run_campaign(root, progress=lambda m: None)
    assert summary.failures == [] and summary.not_built == []
    write_exports(load_campaign(root), root / "outputs", cloud_spacing_m=None, picture=False, report=False)
    return root, evaluate_campaign(root)


@pytest.mark.slow
@pytest.mark.parametrize("prior", ["rough", "none"])
def test_pipeline_places_every_scan_and_finds_trees(tmp_path, prior):
    kw = dict(scans=4, seed=5, prior_error=(4.5, 32.0)) if prior == "rough" else dict(scans=3, seed=6, no_prior=True)
    root, acc = _run(tmp_path, **kw)
    poses = pd.read_csv(root / "outputs" / "poses.csv")
    assert poses["registered"].all(), poses
    s = acc.summary()
    assert s["max_xy_error_m"] <= 0.05 and s["max_z_error_m"] <= 0.10 and s["max_heading_error_deg"] <= 0.5, s
    # quarter resolution (0.44 deg steps): a 20 cm stem at 15 m spans ~2 pixels, fewer than the
    # segment minimum of 4; the full-resolution figures are in benchmarks/results.md
    assert s["detection_rate"] >= 0.6, s
    assert s["dbh_rmse_m"] <= 0.03, s
    regs = pd.read_csv(root / "outputs" / "registrations.csv")
    assert set(regs["status"]) <= {"accepted", "rejected", "failed"}
    residuals = pd.read_csv(root / "outputs" / "residuals.csv")
    assert (residuals["verdict"] == "ok").all()


@pytest.mark.slow
def test_assets_carry_pictures_for_the_dagster_ui(tmp_path):
    """Every stage whose result is a picture-able thing attaches a PNG (inline Markdown image)
    to its materialisation: range image, segment / circle masks, cylinders over the range image
    (JP Fig. 7), occlusion boundaries, network, merged elevation map, DBH histogram, plan."""
    from dagster import DagsterInstance

    root = simulate_campaign(tmp_path / "plot", resolution="quarter", plot_size=20.0, trees=12, scans=2,
                             seed=3, prior_error=(1.0, 10.0))
    assert run_campaign(root, progress=lambda m: None).failures == []
    pictured = {}
    instance = DagsterInstance.get()
    for key in instance.get_asset_keys():
        event = instance.get_latest_materialization_event(key)
        for name, value in (event.asset_materialization.metadata if event else {}).items():
            if "data:image/png;base64," in str(getattr(value, "value", "")):
                pictured.setdefault(key.path[-1], set()).add(name)
    expected = {"range_images": "range_image", "segments": "segment_mask", "circle_models": "circle_mask",
                "cylinder_segments": "cylinders_picture", "occlusion_boundaries": "occlusion_boundaries",
                "optimal_map": "network", "integrated_map": "elevation_map", "tree_list": "dbh_histogram",
                "next_vantage_points": "picture"}
    missing = {stage: name for stage, name in expected.items() if name not in pictured.get(stage, set())}
    assert not missing, missing
