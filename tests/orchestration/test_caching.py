"""Caching users can trust, proven on a real Dagster instance by counting the materialisations
in its event log (issue 6): a parameter change re-runs exactly that stage and what its changed
output feeds; an unchanged output leaves its downstream alone; a new scan runs only its own
per-scan assets and the campaign-level ones; ``forestmap status`` says so beforehand."""

from __future__ import annotations

import pytest
import yaml
from helpers.orchestration import (
    campaign,
    cursor,
    data_versions,
    edit_manifest,
    inputs_of,
    materialised_copy,
    materialised_since,
    status_lines,
    write_manifest,
)

from forestmap_assets.assets.common import CAMPAIGN_STAGES, PAIR_STAGES, PIPELINE, SCAN_STAGES
from forestmap_assets.orchestration.instance import get_instance
from forestmap_assets.orchestration.runner import run_campaign
from forestmap_assets.orchestration.workspace import build_definitions

ALL = [s for s, _ in PIPELINE if s != "retry_pairs"]  # the template's pairs are a priori: no retries
LEVEL = [s for s in CAMPAIGN_STAGES if s != "retry_pairs"]


def _run(root):
    instance = get_instance()
    before = cursor(instance)
    summary = run_campaign(root, progress=lambda m: None)
    assert summary.failures == []
    ran = materialised_since(instance, campaign(root), before)
    assert ran == set(summary.ran)  # the runner's own count agrees with the event log
    return ran


@pytest.mark.slow
def test_template_is_fresh_and_a_rerun_does_nothing(tmp_path, monkeypatch, capsys):
    root = materialised_copy(tmp_path, monkeypatch)
    assert status_lines(root, capsys) == {s: "fresh" for s in ALL}
    assert _run(root) == set()


@pytest.mark.slow
def test_parameter_change_reruns_that_stage_and_only_what_its_output_changes(tmp_path, monkeypatch, capsys):
    root = materialised_copy(tmp_path, monkeypatch)
    defs0 = build_definitions([campaign(root)])
    before = data_versions(defs0, root)
    upstream = {"range_images", "segments", "circle_models", "line_segments", "elevation_maps",
                "occlusion_boundaries", "refine_clouds"}
    downstream = set(ALL) - upstream - {"cylinder_segments"}
    edit_manifest(root, params={"cylinders": {"min_length_m": 3.0}})  # drops the shorter cylinders
    states = status_lines(root, capsys)
    assert states == {s: "fresh" if s in upstream else "stale" for s in ALL}

    ran = _run(root)
    assert {("cylinder_segments", "T"), ("cylinder_segments", "S")} <= ran
    assert {("submaps", "T"), ("submaps", "S")} <= ran  # fewer cylinders, new submaps
    assert not {s for s, _ in ran} & upstream
    # everything else downstream re-ran exactly when one of its inputs got a new data version
    defs = build_definitions([campaign(root)])
    after = data_versions(defs, root)
    for (stage, part) in after:
        if stage not in downstream:
            continue
        changed_inputs = [k for k in inputs_of(defs, root, stage, part) if before[k] != after[k]]
        assert ((stage, part) in ran) == bool(changed_inputs), (stage, part, changed_inputs)
    assert status_lines(root, capsys) == {s: "fresh" for s in ALL}


@pytest.mark.slow
def test_unchanged_output_does_not_make_downstream_stale(tmp_path, monkeypatch, capsys):
    root = materialised_copy(tmp_path, monkeypatch)
    # wall lines are off in the forest preset: a new minimum length changes the code version of
    # line_segments but not its (empty) output
    edit_manifest(root, params={"lines": {"min_length_m": 2.5}})
    states = status_lines(root, capsys)
    assert states["line_segments"] == "stale"
    assert all(states[s] == "fresh" for s in ("range_images", "segments", "circle_models", "cylinder_segments",
                                              "elevation_maps", "refine_clouds"))
    assert all(states[s] == "stale" for s in ("submaps", *LEVEL, *PAIR_STAGES))  # until it has run

    assert _run(root) == {("line_segments", "T"), ("line_segments", "S")}
    assert status_lines(root, capsys) == {s: "fresh" for s in ALL}


@pytest.mark.slow
def test_adding_a_scan_runs_its_own_per_scan_assets_and_the_campaign_level_only(tmp_path, monkeypatch, capsys):
    root = materialised_copy(tmp_path, monkeypatch)
    full = yaml.safe_load((root / "full_manifest.yaml").read_text())
    full["pairs"] = [p for p in full["pairs"] if {p["scan"], p["reference"]} != {"R", "S"}]
    write_manifest(root, full)
    states = status_lines(root, capsys)
    assert all(states[s] == "missing" for s in SCAN_STAGES)  # R's partitions are missing
    assert all(states[s] == "stale" for s in LEVEL)

    ran = _run(root)
    per_scan = {(s, p) for s, p in ran if p in {"T", "S", "R"}}
    assert per_scan == {(s, "R") for s in SCAN_STAGES}
    # issue 17: only the pairs that involve the new scan are registered; T-S is not redone
    pairs = {(s, p) for s, p in ran if p is not None and p not in {"T", "S", "R"}}
    new = {f"{p['scan']}__{p['reference']}" for p in full["pairs"] if "R" in (p["scan"], p["reference"])}
    assert new and pairs == {(s, k) for s in PAIR_STAGES for k in new}
    level = {s for s, p in ran if p is None}
    assert {"candidate_pairs", "optimal_map"} <= level <= set(LEVEL)
    assert status_lines(root, capsys) == {s: "fresh" for s in ALL}
