"""``registration.no_prior_method: fourier``: no-prior candidate pairs are centred on the Fourier
coarse registration of the raw points (men spec 4) and searched in the forest box."""

from __future__ import annotations

import pandas as pd
import pytest
from helpers.orchestration import edit_manifest

from forestmap_assets.access import load_asset
from forestmap_assets.io.campaign import load_campaign
from forestmap_assets.orchestration.runner import run_campaign
from forestmap_assets.outputs.exports import write_exports
from forestmap_assets.sim import simulate_campaign
from forestmap_assets.sim.evaluate import evaluate_campaign


@pytest.mark.slow
def test_fourier_centres_the_no_prior_boxes(tmp_path):
    root = simulate_campaign(tmp_path / "plot", scans=2, trees=24, plot_size=24.0, resolution="quarter",
                             no_prior=True, seed=6)
    edit_manifest(root, params={"registration": {"no_prior_method": "fourier"}, "refine": {"method": "none"}})
    summary = run_campaign(root, progress=lambda m: None)
    assert summary.failures == [] and summary.not_built == []
    write_exports(load_campaign(root), root / "outputs", cloud_spacing_m=None, picture=False, report=False)
    pairs = load_asset("candidate_pairs", campaign=root)
    assert len(pairs) == 1 and pairs["source"].iloc[0] == "fourier"
    assert pairs["hheading_deg"].iloc[0] == 60.0 and pairs["hx"].iloc[0] == 5.0  # the forest box
    truth = pd.read_csv(root / "truth" / "poses.csv").set_index("scan")
    s = truth.loc["S"]  # the reference T is at the origin of the truth frame
    row = pairs.iloc[0]
    assert abs(row["cx"] - s.x) < 0.5 and abs(row["cy"] - s.y) < 0.5
    assert abs((row["cheading_deg"] - s.heading_deg + 180) % 360 - 180) < 3.0
    acc = evaluate_campaign(root).summary()
    assert acc["max_xy_error_m"] <= 0.05 and acc["max_heading_error_deg"] <= 0.5, acc
