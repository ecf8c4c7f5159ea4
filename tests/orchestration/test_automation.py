"""Automation through Dagster's testing APIs (issue 6): the scan-file sensor, the nightly
schedule, the process_campaign job and the campaign-level automation condition."""

from __future__ import annotations

import shutil
from datetime import UTC, datetime

import numpy as np
import pytest
from dagster import (
    RunRequest,
    SensorResult,
    build_schedule_context,
    build_sensor_context,
    evaluate_automation_conditions,
)
from helpers.campaign_files import write_campaign
from helpers.orchestration import edit_manifest, materialised_copy

from forestmap_assets.assets.common import asset_key, job_name
from forestmap_assets.io.campaign import load_campaign
from forestmap_assets.orchestration.automation import (
    PROCESS_JOB,
    automated_definitions,
    nightly_reprocessing,
    process_campaign_job,
)
from forestmap_assets.orchestration.instance import get_instance
from forestmap_assets.orchestration.runner import run_campaign
from forestmap_assets.orchestration.workspace import (
    discover_campaign_folders,
    load_campaigns,
)


def _defs():
    return automated_definitions(load_campaigns(discover_campaign_folders()))


def _tick(defs, instance, cursor=None) -> SensorResult:
    sensor = defs.get_sensor_def("scan_files_sensor")
    with build_sensor_context(instance=instance, definitions=defs, cursor=cursor) as context:
        result = sensor(context)
    assert isinstance(result, SensorResult)
    return result


def _apply(instance, result: SensorResult) -> None:
    """What the daemon does with a sensor result besides launching runs."""
    for req in result.dynamic_partitions_requests or []:
        instance.add_dynamic_partitions(req.partitions_def_name, list(req.partition_keys))
    for event in result.asset_events or []:
        instance.report_runless_asset_event(event)


@pytest.mark.slow
def test_scan_sensor_requests_exactly_the_runs_needed(tmp_path, monkeypatch):
    data = tmp_path / "data"
    root = write_campaign(data / "plot", scans=("T", "S"))
    monkeypatch.setenv("FORESTMAP_DATA_ROOT", str(data))
    instance = get_instance()
    defs = _defs()
    c = load_campaign(root)

    # a loaded campaign never processed: its scan partitions are added and one run per scan
    first = _tick(defs, instance)
    (add,) = first.dynamic_partitions_requests
    assert sorted(add.partition_keys) == ["S", "T"]
    assert sorted((r.job_name, r.partition_key) for r in first.run_requests) == [
        (job_name(c, "scan"), "S"), (job_name(c, "scan"), "T")]
    assert {e.partition for e in first.asset_events} == {"S", "T"}
    _apply(instance, first)

    # once the scans are processed, nothing to do
    run_campaign(root, progress=lambda m: None, stages=["range_images"])
    second = _tick(defs, instance, first.cursor)
    assert not second.run_requests and not second.dynamic_partitions_requests and not second.asset_events

    # one changed scan file: one observation and one run, for that scan only
    arrays = dict(np.load(root / "scans" / "T.npz"))
    arrays["range"] = arrays["range"] * 1.01
    np.savez(root / "scans" / "T.npz", **arrays)
    third = _tick(defs, instance, second.cursor)
    assert [(r.job_name, r.partition_key) for r in third.run_requests] == [(job_name(c, "scan"), "T")]
    assert [e.partition for e in third.asset_events] == ["T"]
    # run keys carry the content hash: the same content is never requested twice, new content is
    (old_t,) = [r.run_key for r in first.run_requests if r.partition_key == "T"]
    assert third.run_requests[0].run_key != old_t

    # a new campaign folder has no definitions in this code location: one process_campaign run
    other = data / "plot-2"
    shutil.copytree(root, other)
    edit_manifest(other, name="second-plot")
    fourth = _tick(defs, instance, third.cursor)
    (req,) = [r for r in fourth.run_requests if r.job_name == PROCESS_JOB]
    assert req.run_config["ops"]["materialise_campaign"]["config"]["folder"] == str(other.resolve())
    assert req.tags["forestmap/campaign"] == "second_plot"
    # ... requested once per content
    fifth = _tick(defs, instance, fourth.cursor)
    assert not [r for r in fifth.run_requests if r.job_name == PROCESS_JOB]

    # an edited manifest of a loaded campaign (new parameters) is handed to the runner too
    edit_manifest(root, params={"cylinders": {"min_length_m": 0.7}})
    sixth = _tick(defs, instance, fifth.cursor)
    assert [r.tags["forestmap/campaign"] for r in sixth.run_requests if r.job_name == PROCESS_JOB] == [c.key]


@pytest.mark.slow
def test_nightly_schedule_and_process_campaign_job(tmp_path, monkeypatch):
    root = materialised_copy(tmp_path, monkeypatch)
    monkeypatch.setenv("FORESTMAP_DATA_ROOT", str(root.parent))
    instance = get_instance()
    night = datetime(2026, 6, 1, 3, 0, tzinfo=UTC)

    def evaluate():
        with build_schedule_context(instance=instance, scheduled_execution_time=night) as context:
            return list(nightly_reprocessing.evaluate_tick(context).run_requests or [])

    assert evaluate() == []  # everything fresh: the night passes without a run

    edit_manifest(root, params={"lines": {"min_length_m": 2.5}})
    (req,) = evaluate()
    assert isinstance(req, RunRequest) and req.job_name == PROCESS_JOB
    config = req.run_config["ops"]["materialise_campaign"]["config"]
    assert config["folder"] == str(root.resolve())

    result = process_campaign_job.execute_in_process(run_config=req.run_config, instance=instance)
    assert result.success
    assert evaluate() == []  # processed: fresh again
    assert (root / "outputs" / "poses.csv").is_file()


@pytest.mark.slow
def test_campaign_level_assets_follow_changed_inputs_only(tmp_path, monkeypatch):
    root = materialised_copy(tmp_path, monkeypatch)
    instance = get_instance()
    c = load_campaign(root)
    defs = automated_definitions([c])
    baseline = evaluate_automation_conditions(defs=defs, instance=instance)
    assert baseline.total_requested == 0

    # new per-scan cylinders (as a sensor-launched scan run would produce them)
    edit_manifest(root, params={"cylinders": {"min_length_m": 3.0}})
    run_campaign(root, progress=lambda m: None, stages=["submaps", "cylinder_segments"])
    c = load_campaign(root)
    defs = automated_definitions([c])
    tick = evaluate_automation_conditions(defs=defs, instance=instance, cursor=baseline.cursor)
    requested = {k.path[-1] for k in (asset_key(c, s) for s in (
        "candidate_pairs", "pairwise_registrations", "optimal_map", "residual_checks", "integrated_map", "tree_list",
    )) if tick.get_num_requested(k)}
    # the assets reading submaps or cylinders; the rest waits for their new data versions (the
    # pair partitions are requested by the scan-file sensor, which observes their inputs)
    assert requested == {"candidate_pairs", "integrated_map"}
