"""Per-scan asset checks (issue 6): enough valid circle models, share of rejected circle models,
enough cylinder segments; ERROR when a scan has none, WARN when it has few."""

from __future__ import annotations

import pandas as pd
import pytest
from dagster import AssetCheckSeverity
from helpers.orchestration import materialised_copy

from forestmap_assets.assets.common import (
    ScanCheckThresholds,
    circle_checks,
    cylinder_checks,
    scan_check_thresholds,
)
from forestmap_assets.io.campaign import load_campaign


def _circles(valid: int, rejected: int) -> pd.DataFrame:
    # an earlier iteration (ignored) and the last one
    last = [True] * valid + [False] * rejected
    return pd.DataFrame({"iteration": [0] * 5 + [1] * len(last), "valid": [False] * 5 + last})


def _by_name(results):
    return {r.check_name: r for r in results}


def test_circle_checks_grade_by_count_and_rejected_share():
    limits = ScanCheckThresholds(min_valid_circles=10, max_rejected_share=0.5, min_cylinders=3)
    good = _by_name(circle_checks(_circles(20, 5), limits))
    assert good["enough_valid_circles"].passed and good["rejected_circle_share"].passed

    few = _by_name(circle_checks(_circles(4, 40), limits))
    assert not few["enough_valid_circles"].passed
    assert few["enough_valid_circles"].severity == AssetCheckSeverity.WARN
    assert not few["rejected_circle_share"].passed
    assert few["rejected_circle_share"].metadata["rejected_share"].value == round(40 / 44, 4)

    none = _by_name(circle_checks(_circles(0, 3), limits))
    assert not none["enough_valid_circles"].passed
    assert none["enough_valid_circles"].severity == AssetCheckSeverity.ERROR
    empty = _by_name(circle_checks(pd.DataFrame(columns=["iteration", "valid"]), limits))
    assert not empty["enough_valid_circles"].passed and empty["rejected_circle_share"].passed


def test_cylinder_check():
    limits = ScanCheckThresholds(min_cylinders=3)
    (ok,) = cylinder_checks(pd.DataFrame({"radius_m": [0.1] * 3}), limits)
    (few,) = cylinder_checks(pd.DataFrame({"radius_m": [0.1]}), limits)
    (none,) = cylinder_checks(pd.DataFrame({"radius_m": []}), limits)
    assert ok.passed and not few.passed and not none.passed
    assert few.severity == AssetCheckSeverity.WARN and none.severity == AssetCheckSeverity.ERROR


@pytest.mark.slow
def test_default_thresholds_pass_on_a_simulated_forest(tmp_path, monkeypatch):
    """The (inferred) defaults accept ordinary quarter-resolution forest scans."""
    from forestmap_assets.access import load_asset

    root = materialised_copy(tmp_path, monkeypatch)
    campaign = load_campaign(root)
    limits = scan_check_thresholds(campaign)
    for scan in campaign.scan_ids:
        circles = load_asset("circle_models", campaign=campaign, scan=scan)
        cylinders = load_asset("cylinder_segments", campaign=campaign, scan=scan)
        assert all(r.passed for r in circle_checks(circles, limits) + cylinder_checks(cylinders, limits))
