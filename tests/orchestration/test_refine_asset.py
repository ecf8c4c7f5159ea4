"""The ``refined_registrations`` asset on a small simulated coloured campaign: range images
materialised through Dagster, a branch-and-bound result placed in the store, the refinement
run as an asset (HICP for colour scans, which a forest campaign asks for with
``refine.method: hicp``) and compared with the truth."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from dagster import materialize

from forestmap_assets.assets.common import asset_key, code_version, pair_partitions
from forestmap_assets.core.geometry import wrap_deg
from forestmap_assets.core.registration.pair_registrations import (
    EXTRA_COLUMNS,
    REGISTRATION_COLUMNS,
)
from forestmap_assets.io.campaign import load_campaign
from forestmap_assets.io.store import default_store_url, write_bundle_atomic
from forestmap_assets.orchestration.definitions import build_definitions
from forestmap_assets.orchestration.instance import get_instance, sync_partitions
from forestmap_assets.orchestration.runner import QUIET
from forestmap_assets.sim import simulate_campaign


def _registrations(truth: pd.DataFrame, offset) -> dict[str, pd.DataFrame]:
    """A branch-and-bound bundle of pair S__T: S located in T's frame, off the truth by ``offset``."""
    t, s = truth.set_index("scan").loc["T"], truth.set_index("scan").loc["S"]
    assert np.allclose([t.x, t.y, t.z, t.heading_deg], 0.0)
    row = dict.fromkeys(REGISTRATION_COLUMNS + EXTRA_COLUMNS, np.nan)
    row.update(scan="S", reference="T", dx=s.x + offset[0], dy=s.y + offset[1], dz=s.z + offset[2],
               dheading_deg=float(wrap_deg(s.heading_deg + offset[3])), sd_x=0.02, sd_y=0.02, sd_z=0.1,
               sd_heading_deg=0.12, status="accepted", reason="", seconds=1.0, n_points=100)
    regs = pd.DataFrame([row], columns=REGISTRATION_COLUMNS + EXTRA_COLUMNS)
    return {"registrations": regs, "levels": pd.DataFrame({"scan": ["S"]}),
            "hypotheses": pd.DataFrame({"scan": ["S"]})}


@pytest.mark.slow
def test_refined_registrations_asset_uses_hicp_on_colour_scans(tmp_path, _isolated_home):
    root = simulate_campaign(tmp_path / "plot", scans=2, trees=20, plot_size=24.0, resolution="half", seed=2,
                             fmt="e57", scanner_kwargs={"colour": True}, write_labels=False)
    assert load_campaign(root).params.refine.method == "point_to_plane"  # the forest's own choice
    manifest = root / "campaign.yaml"
    manifest.write_text(manifest.read_text() + "params:\n  refine:\n    method: hicp\n")
    campaign = load_campaign(root)
    defs = build_definitions([campaign])
    key = asset_key(campaign, "refined_registrations")
    assets = list(defs.assets)
    assert defs.resolve_asset_graph().has(key)
    instance = get_instance()
    sync_partitions(instance, campaign)
    for sid in campaign.scan_ids:
        res = materialize(assets, instance=instance, partition_key=sid, resources=defs.resources,
                          selection=[asset_key(campaign, "range_images")], run_config=QUIET)
        assert res.success

    truth = pd.read_csv(root / "truth" / "poses.csv")
    offset = np.array([0.03, -0.02, 0.08, 0.1])
    store = default_store_url()
    from upath import UPath

    # the pair partition S__T (issue 17) with a branch-and-bound result in the store
    instance.add_dynamic_partitions(pair_partitions(campaign).name, ["S__T"])
    write_bundle_atomic(_registrations(truth, offset),
                        UPath(store) / campaign.key / "pairwise_registrations" / "S__T.bundle")
    res = materialize(assets, instance=instance, resources=defs.resources, selection=[key], partition_key="S__T",
                      run_config=QUIET)
    assert res.success
    out = res.output_for_node(key.to_python_identifier())
    ref, regs = out["refinements"], out["registrations"]
    assert len(ref) == 1 and ref["method"].iloc[0] == "hicp" and ref["used"].iloc[0] == "refined"
    assert ref["fit_refined_m"].iloc[0] < ref["fit_bnb_m"].iloc[0]
    s = truth.set_index("scan").loc["S"]
    acc = regs[regs["status"] == "accepted"].iloc[0]
    assert bool(acc["refined"]) and acc["refine_method"] == "hicp"
    err = np.array([acc["dx"] - s.x, acc["dy"] - s.y, acc["dz"] - s.z])
    assert np.linalg.norm(err) < 0.25 * np.linalg.norm(offset[:3])  # much closer than the B&B pose
    assert abs(wrap_deg(acc["dheading_deg"] - s.heading_deg)) < 0.05
    assert 0 < acc["sd_x"] < 0.02  # its own, smaller uncertainty
    meta = res.asset_materializations_for_node(key.to_python_identifier())[0].metadata
    assert meta["used"].value == "refined" and meta["method"].value == "hicp"
    assert code_version(campaign, "refined_registrations").startswith("v8-")
